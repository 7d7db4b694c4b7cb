"""The documentation stays true: references point at files in the repository, the keys table at the schema."""

from __future__ import annotations

import re

import pytest
import yaml

from cosim.scenario.model import Scenario
from tests.helpers import REPO

SOURCES = [
    *REPO.glob("*.md"),
    *REPO.glob("Makefile"),
    *(p for d in ("cosim", "sensors", "exporters", "scenarios", "sweeps", "docs", "examples", "benchmarks", "tests")
      for p in (REPO / d).rglob("*") if p.suffix in (".py", ".yaml", ".md", ".toml")),
]


def _text(path) -> str:
    return path.read_text(encoding="utf-8")


#: the design notes and shared folder the project was planned from; they are not in the repository
OUTSIDE = re.compile(r"\bdesign\.md|\.\./shared")


def test_nothing_points_outside_the_repository():
    """Code and docs cite docs/*.md; design notes outside the repository are not there for users."""
    me = REPO / "tests" / "test_docs.py"
    bad = [f"{p.relative_to(REPO)}:{n}" for p in SOURCES if p != me
           for n, line in enumerate(_text(p).splitlines(), 1) if OUTSIDE.search(line)]
    assert not bad, f"references to files outside the repository: {bad}"


def test_every_cited_doc_and_section_exists():
    headings = {p.name: {m.group(1) for m in re.finditer(r"^#+ (\d+(?:\.\d+)?)[. ]", _text(p), re.M)}
                for p in (REPO / "docs").glob("*.md")}
    cited = 0
    for p in SOURCES:
        for m in re.finditer(r"docs/(\w+\.md)(?: sections? ([\d.]+)(?:(?:-| and |, )([\d.]+))*)?", _text(p)):
            cited += 1
            assert m.group(1) in headings, f"{p.relative_to(REPO)} cites docs/{m.group(1)}, which does not exist"
            for section in filter(None, (m.group(2), m.group(3))):
                assert section in headings[m.group(1)], f"{p.relative_to(REPO)}: no section {section} in {m.group(1)}"
    assert cited > 10


def _keys_table() -> list[tuple[str, str]]:
    readme = _text(REPO / "README.md")
    table = readme.split("### Scenario keys you will use", 1)[1].split("\n\n", 3)[2]
    rows = [line.split(" | ") for line in table.splitlines()[2:]]
    return [(row[0].strip("| `"), row[1]) for row in rows]


def _lookup(data, dotted: str):
    for part in dotted.split("."):
        data = data[int(part)] if isinstance(data, list) else data[part]
    return data


#: Keys the resolved scenario leaves out while they are empty (so that episodes without them keep their bytes).
LEFT_OUT_WHILE_EMPTY = {"agents.vehicles.rigs", "agents.rsus.rigs"}


def test_the_readme_keys_table_matches_the_schema():
    defaults = Scenario(name="x").model_dump(mode="json")
    rows = _keys_table()
    assert "sensors.image_scale" in dict(rows) and len(rows) >= 20
    checked = 0
    for key, default in rows:
        if key in LEFT_OUT_WHILE_EMPTY:
            assert key.rsplit(".", 1)[1] not in _lookup(defaults, key.rsplit(".", 1)[0]), key
            value = {}
        else:
            value = _lookup(defaults, key)  # KeyError: the table names a key the schema does not have
        literal = re.match(r"`([^`]*)`", default)
        if literal:
            assert yaml.safe_load(literal.group(1)) == pytest.approx(value), key
            checked += 1
    assert checked >= 20


def test_the_readme_sweep_example_plans_as_the_readme_says(tmp_path):
    """The README's sweep section: its YAML example is a valid sweep (every key the section describes is in it),
    and its plan has the sizes, splits and level counts the section states."""
    from collections import Counter

    from cosim.batch.plan import plan_file

    section = _text(REPO / "README.md").split("## Sweeps: the file `cosim batch` reads", 1)[1].split("\n## ", 1)[0]
    example = section.split("```yaml\n", 1)[1].split("```", 1)[0]
    data = yaml.safe_load(example)
    assert {"name", "seed", "base", "set", "axes", "vary", "count", "split"} <= set(data)
    assert any("levels" in axis for axis in data["axes"].values()) and "hours:" in example
    path = tmp_path / "mini.yaml"
    path.write_text(example)
    plan = plan_file(path)
    flat = " ".join(section.split())  # the claims, whatever the line breaks
    n, seconds, combos = re.search(r"This one plans (\d+) episodes of (\d+) s over (\d+) combinations",
                                   flat).groups()
    assert (len(plan.episodes), plan.combinations) == (int(n), int(combos))
    assert {e.duration_s for e in plan.episodes} == {float(seconds)}
    splits = Counter(e.split for e in plan.episodes)
    assert f"{splits['train']} in `train` and {splits['val']} in `val`" in flat, splits
    strategy = Counter(e.labels["strategy"] for e in plan.episodes)
    train = Counter(e.labels["strategy"] for e in plan.episodes if e.split == "train")
    assert f"`hover` {strategy['hover']} and `patrol` {strategy['patrol']}" in flat, strategy
    assert f"(in `train` {train['hover']} and {train['patrol']}, as the weights say" in flat, train
    weather = Counter(e.labels["weather"] for e in plan.episodes)
    assert f"`clear` {weather['clear']} and `foggy` {weather['foggy']}" in flat, weather
    assert any(e.file == "train/train-foggy-patrol-0002.mcap" for e in plan.episodes)
