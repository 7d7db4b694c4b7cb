"""Property: a mutated scenario or sweep file gives exit 0 or exit 2 with one message, never a traceback.

Mutations of the shipped files: wrong types, extreme numbers, NaN and infinity, control characters, deep
nesting, deleted and duplicated keys, one to three per file. The CLI runs in this process on paths that
build no world and start no worker (``cosim run --dry-run``, ``cosim batch --dry-run --calibrate-s 0``).
Seeded (derandomize) and bounded (max_examples), so every run tries the same files.
"""

from __future__ import annotations

import collections
import copy
import math
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cosim.cli import main
from cosim.scenario import load_scenario
from tests.helpers import REPO, SCENARIOS

SCENARIO_EXAMPLES = 120
SWEEP_EXAMPLES = 40
DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
#: The same examples every run (derandomize, no example database), no per-example deadline on a loaded machine.
BOUNDED = settings(deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                          HealthCheck.data_too_large])
KINDS = ("wrong_type", "extreme_number", "non_finite", "control_char", "deep_nesting", "delete_key",
         "duplicate_key")

WRONG_TYPES = ["text", "", [], {}, [1, "a"], {"x": 1}, True, None, 7, -3]
EXTREME = [0, -1, 2**31, 2**63, -(2**63), 2**64 + 1, 10**400, 1e308, -1e308, 5e-324, 1e-320]
NON_FINITE = [math.nan, math.inf, -math.inf]
CONTROL = ["\x00", "\x01", "\x07", "\x08", "\x1b", "\x7f", "\x85", "\ufeff", "\u2028", "\x0c"]

# the tests that count what the properties tried read RUNS after them: one worker, in file order
pytestmark = pytest.mark.resource("input_fuzz")

RUNS: collections.Counter[str] = collections.Counter()


def key_paths(value, path=()):
    """Every key path into plain data (mappings and lists), the root excluded."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield (*path, k)
            yield from key_paths(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield (*path, i)
            yield from key_paths(v, (*path, i))


def replace_at(data, path, new):
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = new


def delete_at(data, path):
    node = data
    for k in path[:-1]:
        node = node[k]
    del node[path[-1]]


def nested(depth: int, leaf):
    out = leaf
    for i in range(depth):
        out = [out] if i % 2 else {"k": out}
    return out


@st.composite
def mutated_text(draw, seeds: list[dict]) -> str:
    """A YAML text: one of ``seeds`` with one to three mutations."""
    data = copy.deepcopy(draw(st.sampled_from(seeds)))
    text_edits: list[tuple[str, object]] = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(KINDS))
        RUNS[kind] += 1
        paths = list(key_paths(data))
        if kind in ("control_char", "duplicate_key"):
            text_edits.append((kind, draw(st.sampled_from(CONTROL)) if kind == "control_char" else None))
            continue
        if not paths:
            continue
        path = draw(st.sampled_from(paths))
        if kind == "delete_key":
            delete_at(data, path)
        elif kind == "wrong_type":
            replace_at(data, path, draw(st.sampled_from(WRONG_TYPES)))
        elif kind == "extreme_number":
            replace_at(data, path, draw(st.sampled_from(EXTREME)))
        elif kind == "non_finite":
            replace_at(data, path, draw(st.sampled_from(NON_FINITE)))
        elif kind == "deep_nesting":
            depth = draw(st.sampled_from([30, 100, 3000]))
            if depth > 100:  # deeper than PyYAML's own dumper goes: written into the text below
                text_edits.append(("deep_text", depth))
            else:
                replace_at(data, path, nested(depth, 1))
    text = yaml.dump(data, Dumper=DUMPER, sort_keys=False, width=1_000_000)
    lines = text.splitlines(keepends=True)
    for kind, arg in text_edits:
        at = draw(st.integers(0, max(0, len(lines) - 1)))
        if not lines:
            break
        if kind == "duplicate_key":
            lines.insert(at, lines[at])
        elif kind == "control_char":
            col = draw(st.integers(0, len(lines[at])))
            lines[at] = lines[at][:col] + str(arg) + lines[at][col:]
        elif kind == "deep_text" and ": " in lines[at]:
            key = lines[at].split(": ", 1)[0]
            lines[at] = f"{key}: {'[' * int(arg)}1{']' * int(arg)}\n"
    return "".join(lines)


def run_cli(capsys, args: list[str]) -> tuple[int, str]:
    try:
        status = main(args)
    except SystemExit as exc:  # argparse usage errors
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.err


def check(status: int, err: str, text: str) -> None:
    assert "Traceback" not in err, (err, text)
    assert status in (0, 2), (status, err, text)
    if status == 2:  # one message: one line, or a list of the problems under "FILE: N problems:"
        lines = err.strip().splitlines()
        assert lines[0].startswith("cosim: error: "), (err, text)
        if len(lines) > 1:
            assert lines[0].endswith(" problems:") and all(line.startswith("  ") for line in lines[1:]), (err, text)


def _scenario_seeds() -> list[dict]:
    raw = yaml.safe_load((SCENARIOS / "default.yaml").read_text())
    raw["extends"] = str(SCENARIOS / "base" / "paper.yaml")
    return [raw, load_scenario("default").resolved]


def _sweep_seeds() -> list[dict]:
    out = []
    for name in ("smoke", "airv2x_like"):
        data = yaml.safe_load((REPO / "sweeps" / f"{name}.yaml").read_text())
        base = data["base"]
        data["base"] = [str((REPO / "sweeps" / b).resolve()) for b in base] if isinstance(base, list) else \
            str((REPO / "sweeps" / base).resolve())
        data.pop("hours", None)
        data["count"] = 4
        out.append(data)
    return out


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def run_mutated(capsys, workdir: Path, kind: str, text: str, *args: str) -> None:
    """Write ``text`` as ``<kind>.yaml``, run ``cosim ARGS FILE-ARGS`` and check the outcome."""
    f = workdir / f"{kind}.yaml"
    f.write_text(text, encoding="utf-8", errors="surrogatepass")
    RUNS[f"{kind}_files"] += 1
    status, err = run_cli(capsys, [args[0], str(f), *args[1:]])
    check(status, err, text)


@settings(BOUNDED, max_examples=SCENARIO_EXAMPLES)
@given(text=mutated_text(_scenario_seeds()))
def test_mutated_scenarios_exit_0_or_2_without_a_traceback(capsys, workdir, text):
    run_mutated(capsys, workdir, "scenario", text, "run", "--dry-run", "--out", str(workdir / "out"))


@settings(BOUNDED, max_examples=SWEEP_EXAMPLES)
@given(text=mutated_text(_sweep_seeds()))
def test_mutated_sweeps_exit_0_or_2_without_a_traceback(capsys, workdir, text):
    run_mutated(capsys, workdir, "sweep", text, "batch", "--out", str(workdir / "batch"), "--dry-run",
                "--calibrate-s", "0")


def test_every_kind_of_mutation_was_tried():
    """Runs after the two properties (file order): each kind of mutation was applied many times."""
    if not RUNS["scenario_files"] or not RUNS["sweep_files"]:
        pytest.skip("run with the property tests above")
    assert RUNS["scenario_files"] >= SCENARIO_EXAMPLES and RUNS["sweep_files"] >= SWEEP_EXAMPLES, RUNS
    assert all(RUNS[k] >= 10 for k in KINDS), RUNS


# ------------------------------------------------------------------------------ batch into bad output folders

OUT_EXAMPLES = 30
OUT_KINDS = ("a_file", "under_a_file", "proc", "sys", "dev_null", "nul_char", "long_name", "deep_under_file")


@st.composite
def bad_out(draw, root: Path) -> tuple[str, str]:
    """(kind, path) of an output folder no episode can be written into."""
    kind = draw(st.sampled_from(OUT_KINDS))
    RUNS[f"out_{kind}"] += 1
    name = draw(st.text(alphabet="abcxyz_-.0123456789", min_size=1, max_size=12).filter(lambda s: s not in (".", "..")))
    a_file = root / "a_file"
    if kind == "a_file":
        return kind, str(a_file)
    if kind == "under_a_file":
        return kind, str(a_file / name)
    if kind == "deep_under_file":
        return kind, str(a_file.joinpath(*[name] * draw(st.integers(2, 20))))
    if kind == "proc":
        return kind, f"/proc/{name}x/{name}"
    if kind == "sys":
        return kind, f"/sys/{name}x"
    if kind == "dev_null":
        return kind, "/dev/null" + draw(st.sampled_from(["", "/x"]))
    if kind == "nul_char":
        return kind, str(root / f"{name}\x00{name}")
    return kind, str(root / ("n" * draw(st.integers(256, 5000))))


@settings(BOUNDED, max_examples=OUT_EXAMPLES)
@given(data=st.data(), dry_run=st.booleans())
def test_batch_into_a_bad_output_folder_exits_2_without_a_traceback(capsys, workdir, data, dry_run):
    (workdir / "a_file").write_text("not a folder")
    kind, out = data.draw(bad_out(workdir))
    args = ["batch", "smoke", "--out", out, "--count", "1", *(["--dry-run", "--calibrate-s", "0"] if dry_run else [])]
    status, err = run_cli(capsys, args)
    assert status == 2, (kind, out, status, err)
    check(status, err, out)
    assert "output folder" in err, (kind, err)


def test_every_kind_of_bad_output_folder_was_tried():
    """Runs after the property above (file order)."""
    if not any(RUNS[f"out_{k}"] for k in OUT_KINDS):
        pytest.skip("run with the property test above")
    assert all(RUNS[f"out_{k}"] >= 1 for k in OUT_KINDS), RUNS
