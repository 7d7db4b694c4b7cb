"""Load a scenario: YAML with line marks, ``extends:`` overlays and ``--set`` overrides.

The result is one frozen :class:`~cosim.scenario.model.Scenario`. Every problem becomes a
:class:`~cosim.errors.ScenarioError` naming the dotted key path and the file and line it came from.
"""

from __future__ import annotations

import copy
import datetime
import difflib
import json
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from cosim.errors import ScenarioError
from cosim.scenario.model import (
    DRONE_STRATEGIES,
    EVENT_KINDS,
    EnvironmentSpec,
    MapSpec,
    RuleError,
    Scenario,
    complete_rigs,
    merge_fields,
)

Key = tuple[str | int, ...]



def scenario_dirs() -> list[Path]:
    """Where shipped scenarios live: $COSIM_SCENARIO_PATH (os.pathsep-separated), then the checkout's scenarios/."""
    dirs = [Path(p) for p in os.environ.get("COSIM_SCENARIO_PATH", "").split(os.pathsep) if p]
    return [*dirs, Path(__file__).resolve().parents[2] / "scenarios"]


@dataclass
class YamlDoc:
    """Plain YAML data plus, for every key path, the (source, line) it was written at.

    Shared by scenario and sweep loading (:mod:`cosim.batch.sweep`)."""

    data: dict[str, Any]
    marks: dict[Key, tuple[str, int]] = field(default_factory=dict)
    before_overrides: dict[str, Any] | None = None  # ``data`` as it was before the first override


#: Keys that set an episode's conditions -> (name in the episode metadata, the schema's default).
CONDITION_KEYS: dict[Key, tuple[str, str]] = {
    ("map", "kind"): ("environment", MapSpec.model_fields["kind"].default),
    ("environment", "weather"): ("weather", EnvironmentSpec.model_fields["weather"].default),
    ("environment", "lighting"): ("lighting", EnvironmentSpec.model_fields["lighting"].default),
}


@dataclass(frozen=True)
class LoadedScenario:
    """A validated scenario and the merged plain data it was built from (for the episode attachment)."""

    scenario: Scenario
    source: Path | None
    resolved: dict[str, Any]
    base_dir: Path

    def resolve_path(self, value: str) -> Path:
        """A path from the scenario (e.g. ``map.file``), relative to the scenario's folder."""
        p = Path(value)
        return p if p.is_absolute() else (self.base_dir / p).resolve()


class _LineLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys (a silent overwrite hides typos)."""


def _construct(node: yaml.Node, source: str, path: Key, marks: dict[Key, tuple[str, int]]) -> Any:
    marks[path] = (source, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Any] = {}
        for key_node, value_node in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                raise ScenarioError("YAML merge keys (<<) are not supported; use extends:", path=dotted(path),
                                    line=key_node.start_mark.line + 1, source=source)
            if not isinstance(key_node, yaml.ScalarNode):
                raise ScenarioError("keys must be plain strings", path=dotted(path),
                                    line=key_node.start_mark.line + 1, source=source)
            key = key_node.value
            if key in out:
                raise ScenarioError(f"key {key!r} appears twice", path=dotted((*path, key)),
                                    line=key_node.start_mark.line + 1, source=source)
            child = (*path, key)
            out[key] = _construct(value_node, source, child, marks)
            marks[child] = (source, key_node.start_mark.line + 1)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_construct(v, source, (*path, i), marks) for i, v in enumerate(node.value)]
    line = node.start_mark.line + 1
    try:
        value = yaml.SafeLoader(" ").construct_object(node, deep=True)
    except yaml.MarkedYAMLError as exc:
        raise ScenarioError(f"invalid value: {exc.problem}", path=dotted(path), line=line, source=source) from None
    except (ValueError, TypeError, OverflowError) as exc:  # e.g. a tagged value such as !!float abc, a 13th month
        raise ScenarioError(f"invalid value {node.value!r}: {exc}", path=dotted(path), line=line,
                            source=source) from None
    if isinstance(value, datetime.date):  # YAML reads 2024-01-02 as a date: keep the text, no field is a date
        return node.value
    if not isinstance(value, str | int | float | bool | None):
        raise ScenarioError(f"unsupported value of type {type(value).__name__} (tag {node.tag})", path=dotted(path),
                            line=line, source=source)
    return value


def dotted(path: Iterable[str | int]) -> str:
    return ".".join(str(p) for p in path)


#: Larger YAML files are refused unread (a scenario or sweep is a few kB; this catches a wrong file).
MAX_YAML_BYTES = 4 * 1024 * 1024


#: Deepest ``[``/``{`` nesting read (PyYAML's scanner takes time quadratic in it; scenarios need 5).
MAX_FLOW_DEPTH = 100
MAX_INDENT = 400  # [columns] of leading spaces, the same bound for block nesting


def _deeper_than(text: str, limit: int) -> int | None:
    """The 1-based line where flow brackets nest deeper than ``limit``, else None (quotes and comments skipped)."""
    depth, line, quote = 0, 1, ""
    prev = "\n"
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c == "\n":
            line += 1
        if quote:
            if c == "\\" and quote == '"':
                i += 1
            elif c == quote:
                quote = ""
        elif c in "'\"" and (prev in " \t\n[{,:" or depth):
            quote = c
        elif c == "#" and prev in " \t\n":
            j = text.find("\n", i)
            i = n if j < 0 else j
            continue
        elif c in "[{":
            depth += 1
            if depth > limit:
                return line
        elif c in "]}" and depth:
            depth -= 1
        prev = c
        i += 1
    return None


def parse_yaml(path: Path) -> YamlDoc:
    """Parse a YAML mapping keeping line marks; every problem (unreadable, binary, control characters,
    invalid YAML, too deep) is one :class:`ScenarioError` naming the file and, where known, the line."""
    source = str(path)
    try:
        if path.stat().st_size > MAX_YAML_BYTES:
            raise ScenarioError(f"file is larger than {MAX_YAML_BYTES // (1024 * 1024)} MiB: not a scenario",
                                source=source)
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ScenarioError(f"file not found: {path}", source=source) from None
    except OSError as exc:
        raise ScenarioError(f"cannot read {path}: {exc.strerror}", source=source) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ScenarioError(f"not a text file: byte {exc.start} is not UTF-8 (0x{raw[exc.start]:02x})", line=line,
                            source=source) from None
    too_deep = _deeper_than(text, MAX_FLOW_DEPTH)
    if too_deep is not None:
        raise ScenarioError(f"invalid YAML: brackets nested more than {MAX_FLOW_DEPTH} levels deep", line=too_deep,
                            source=source)
    for number, row in enumerate(text.splitlines(), 1):
        if len(row) - len(row.lstrip(" ")) > MAX_INDENT:
            raise ScenarioError(f"invalid YAML: indented more than {MAX_INDENT} columns (nested too deeply)",
                                line=number, source=source)
    try:
        node = yaml.compose(text, Loader=_LineLoader)
        if node is None:
            raise ScenarioError("the file is empty", source=source)
        if not isinstance(node, yaml.MappingNode):
            raise ScenarioError("a scenario must be a YAML mapping", line=node.start_mark.line + 1, source=source)
        marks: dict[Key, tuple[str, int]] = {}
        data = _construct(node, source, (), marks)
    except yaml.reader.ReaderError as exc:  # a NUL or another control character
        line = text[: exc.position].count("\n") + 1
        raise ScenarioError(f"invalid YAML: control character U+{int(exc.character):04X} is not allowed in "
                            "a YAML file", line=line, source=source) from None
    except yaml.MarkedYAMLError as exc:
        line = exc.problem_mark.line + 1 if exc.problem_mark else None
        raise ScenarioError(f"invalid YAML: {exc.problem}", line=line, source=source) from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"invalid YAML: {exc}", source=source) from None
    except RecursionError:
        raise ScenarioError("invalid YAML: nested too deeply", source=source) from None
    return YamlDoc(data, marks)


def load_with_extends(path: Path) -> YamlDoc:
    """Parse a scenario file with its ``extends:`` chain merged in, rigs completed (:func:`complete_rigs`)."""
    doc = _load_with_extends(path, ())
    doc.data["sensors"] = complete_rigs(doc.data.get("sensors", {}))
    return doc


def _load_with_extends(path: Path, seen: tuple[Path, ...]) -> YamlDoc:
    path = path.resolve()
    if path in seen:
        chain = " -> ".join(str(p) for p in (*seen, path))
        raise ScenarioError(f"extends: forms a cycle: {chain}", path="extends", source=str(path))
    doc = parse_yaml(path)
    parent = doc.data.pop("extends", None)
    if parent is None:
        return doc
    if not isinstance(parent, str):
        src, line = doc.marks[("extends",)]
        raise ScenarioError("extends must be a path to a scenario file", path="extends", line=line, source=src)
    src, line = doc.marks[("extends",)]
    try:
        base_path = (path.parent / parent).resolve()
        found = base_path.is_file()
    except (OSError, ValueError) as exc:  # a name too long for the file system, a NUL in it
        shown = parent if len(parent) <= 80 else f"{parent[:60]}... ({len(parent)} characters)"
        raise ScenarioError(f"cannot open the base scenario {shown!r}: {getattr(exc, 'strerror', None) or exc}",
                            path="extends", line=line, source=src) from None
    if not found:
        raise ScenarioError(f"base scenario not found: {base_path}", path="extends", line=line, source=src)
    base = _load_with_extends(base_path, (*seen, path))
    marks = dict(base.marks)
    marks.update(doc.marks)
    return YamlDoc(merge_fields(base.data, doc.data), marks)


def apply_override(doc: YamlDoc, assignment: str) -> None:
    """Apply one ``a.b.0.c=value`` override; the value is parsed as YAML (``3``, ``true``, ``[1, 2]``)."""
    key, sep, raw = assignment.partition("=")
    source = f"--set {_printable(assignment)}"
    if not sep or not key.strip():
        raise ScenarioError("expected KEY=VALUE, for example --set environment.weather=foggy", source=source)
    parts: list[str | int] = [int(p) if p.isdigit() else p for p in key.strip().split(".")]
    if _deeper_than(raw, MAX_FLOW_DEPTH) is not None:
        raise ScenarioError(f"value is not valid YAML: brackets nested more than {MAX_FLOW_DEPTH} levels deep",
                            path=_printable(key), source=source)
    try:
        node = yaml.compose(raw, Loader=_LineLoader) if raw.strip() else None
        value = _construct(node, source, tuple(parts), {}) if node is not None else None if raw.strip() else ""
    except yaml.reader.ReaderError as exc:
        raise ScenarioError(f"value is not valid YAML: control character U+{int(exc.character):04X} is not allowed",
                            path=_printable(key), source=source) from None
    except yaml.MarkedYAMLError as exc:
        raise ScenarioError(f"value is not valid YAML: {exc.problem}", path=_printable(key), source=source) from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"value is not valid YAML: {exc}", path=_printable(key), source=source) from None
    except RecursionError:
        raise ScenarioError("value is nested too deeply", path=_printable(key), source=source) from None
    if doc.before_overrides is None:
        doc.before_overrides = copy.deepcopy(doc.data)
    node: Any = doc.data
    for i, part in enumerate(parts[:-1]):
        if isinstance(node, list):
            if not isinstance(part, int) or part >= len(node):
                raise ScenarioError(f"no list item {part} (the list has {len(node)})",
                                    path=dotted(parts[: i + 1]), source=source)
            node = node[part]
        elif isinstance(node, dict):
            node = node.setdefault(part, {})
        else:
            raise ScenarioError("cannot set a key inside a plain value", path=dotted(parts[: i + 1]), source=source)
    last = parts[-1]
    if isinstance(node, list):
        if not isinstance(last, int) or last >= len(node):
            raise ScenarioError(f"no list item {last} (the list has {len(node)})", path=key, source=source)
        node[last] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise ScenarioError("cannot set a key inside a plain value", path=key, source=source)
    for k in [k for k in doc.marks if k[: len(parts)] == tuple(parts)]:
        del doc.marks[k]
    doc.marks[tuple(parts)] = (source, None)  # type: ignore[assignment]


def _printable(text: str, limit: int = 120) -> str:
    """``text`` for an error message: control characters escaped, long text shortened."""
    shown = text if text.isprintable() else text.encode("unicode_escape").decode("ascii")
    return shown if len(shown) <= limit else f"{shown[: limit - 20]}... ({len(text)} characters)"


_UNION_TAGS = frozenset((*DRONE_STRATEGIES, *EVENT_KINDS))


def _is_pydantic_artefact(part: str | int) -> bool:
    """Union tags and validator names that pydantic puts into error locations (``function-after[...]``)."""
    return isinstance(part, str) and (part in _UNION_TAGS or "[" in part)


def clean_error_loc(loc: Sequence[str | int], data: Any) -> list[str | int]:
    """An error location as a key path into the data: data keys and list indices, plus a final missing
    or unknown key; pydantic's union tags and validator names dropped."""
    out: list[str | int] = []
    node = data
    for i, part in enumerate(loc):
        in_dict = isinstance(node, dict) and part in node
        in_list = isinstance(node, list) and isinstance(part, int) and 0 <= part < len(node)
        if in_dict or in_list:
            out.append(part)
            node = node[part]
        elif i == len(loc) - 1 and not _is_pydantic_artefact(part):
            out.append(part)
    return out


def _model_at(path: Sequence[str | int], data: Any) -> type[BaseModel] | None:
    """The pydantic model class that validates the mapping at ``path`` (for key suggestions)."""
    from cosim.scenario import model as m

    cls: Any = Scenario
    node = data
    for part in path:
        if isinstance(part, int):
            node = node[part] if isinstance(node, list) and part < len(node) else None
            continue
        if not (isinstance(cls, type) and issubclass(cls, BaseModel)) or part not in cls.model_fields:
            return None
        node = node.get(part) if isinstance(node, dict) else None
        ann = cls.model_fields[part].annotation
        if part == "drones":
            cls = None
            continue
        cls = ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None
        if cls is None and ann is not None:
            for arg in getattr(ann, "__args__", ()):
                if isinstance(arg, type) and issubclass(arg, BaseModel):
                    cls = arg
    if cls is None and isinstance(node, dict) and "strategy" in node:
        cls = {"hover": m.HoverDrone, "patrol": m.PatrolDrone, "escort": m.EscortDrone}.get(node["strategy"])
    if cls is None and len(path) >= 2 and path[-2] == "drones" and isinstance(node, dict):
        cls = {"hover": m.HoverDrone, "patrol": m.PatrolDrone, "escort": m.EscortDrone}.get(
            node.get("strategy", "hover"))
    return cls


def unknown_key_message(bad: str, owner: type[BaseModel] | None) -> str:
    """``unknown key 'wether'; did you mean 'weather'? (known keys: ...)`` for the model that owns the mapping."""
    if owner is None:
        return f"unknown key {bad!r}"
    known = list(owner.model_fields)
    close = difflib.get_close_matches(bad, known, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown key {bad!r}{hint} (known keys: {', '.join(known)})"


def error_message(err: dict[str, Any], path: list[str | int], data: Any) -> str:
    kind = err["type"]
    if kind == "extra_forbidden":
        return unknown_key_message(str(path[-1]), _model_at(path[:-1], data))
    if kind == "missing":
        return "required key is missing"
    if kind in ("literal_error", "enum"):
        return f"{err['msg']}, got {json.dumps(err.get('input'))}"
    if kind == "union_tag_invalid":
        key = str(err["ctx"].get("discriminator", "'strategy'")).strip("'")
        return f"unknown {key} {err['ctx']['tag']!r}; expected one of {err['ctx']['expected_tags']}"
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    got = err.get("input")
    if kind not in ("value_error", "assertion_error") and not isinstance(got, dict | list):
        msg += f", got {json.dumps(got, default=str)}"
    return msg


def located_error(
    exc: ValidationError,
    doc: YamlDoc,
    *,
    error_cls: type[ScenarioError] = ScenarioError,
    clean: Callable[[Sequence[str | int], Any], list[str | int]] = clean_error_loc,
    message: Callable[[dict[str, Any], list[str | int], Any], str] = error_message,
) -> ScenarioError:
    """One error for a failed validation: the first problem, its dotted key path and the file and line
    it was written at (``clean`` and ``message`` let other YAML formats, such as sweeps, adapt both)."""
    err = exc.errors(include_url=False)[0]
    path = clean(err["loc"], doc.data)
    ctx_error = (err.get("ctx") or {}).get("error")
    if isinstance(ctx_error, RuleError):
        path = path + [int(p) if p.isdigit() else p for p in ctx_error.path.split(".")]
    text = message(err, path, doc.data)
    source, line = "", None
    for n in range(len(path), -1, -1):
        mark = doc.marks.get(tuple(path[:n]))
        if mark is not None:
            source, line = mark
            break
    more = len(exc.errors()) - 1
    if more:
        text += f" (and {more} more problem{'s' if more > 1 else ''})"
    return error_cls(text, path=dotted(path), line=line, source=source)


def find_yaml(name_or_path: str | Path, dirs: Iterable[Path]) -> Path | None:
    """A file path as given, else ``NAME`` or ``NAME.yaml`` in the first of ``dirs`` that has it."""
    p = Path(name_or_path)
    for cand in (p, *(c for d in dirs for c in (d / p, d / f"{p}.yaml"))):
        try:
            if cand.is_file():
                return cand
        except (OSError, ValueError):  # a name too long for the file system, a NUL in it: not a file
            continue
    return None


def find_scenario(name_or_path: str | Path) -> Path:
    """A scenario path as given, or the name of a shipped one (``town_rural_night``)."""
    found = find_yaml(name_or_path, scenario_dirs())
    if found is not None:
        return found
    raise ScenarioError(f"scenario not found: {name_or_path} (see `cosim scenarios` for the shipped ones)",
                        source=str(name_or_path))


def load_scenario(path: str | Path, overrides: Sequence[str] = ()) -> LoadedScenario:
    """Load, overlay, override and validate a scenario file."""
    file = find_scenario(path).resolve()
    doc = load_with_extends(file)
    for assignment in overrides:
        apply_override(doc, assignment)
    return validate_doc(doc, file)


def load_scenario_data(data: dict[str, Any], overrides: Sequence[str] = ()) -> LoadedScenario:
    """Validate a scenario given as plain data (as stored in an episode or built by a sweep)."""
    doc = YamlDoc(json.loads(json.dumps(data)))
    for assignment in overrides:
        apply_override(doc, assignment)
    return validate_doc(doc, None)


def validate_doc(doc: YamlDoc, file: Path | None) -> LoadedScenario:
    try:
        scenario = Scenario.model_validate(doc.data)
    except ValidationError as exc:
        raise located_error(exc, doc) from None
    scenario = describe_overridden_conditions(scenario, doc)
    resolved = scenario.model_dump(mode="json")
    return LoadedScenario(scenario, file, resolved, file.parent if file else Path.cwd())


def _condition_values(data: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for path, (name, default) in CONDITION_KEYS.items():
        node: Any = data
        for part in path:
            node = node.get(part) if isinstance(node, dict) else None
        out[name] = default if node is None else node
    return out


def describe_overridden_conditions(scenario: Scenario, doc: YamlDoc) -> Scenario:
    """The scenario with its description amended when overrides changed its conditions.

    A description is written for the file's conditions ("rural roads at night"); after ``--set
    environment.lighting=day`` (or a sweep's axis) it would describe another episode. The amended
    text keeps the author's words and says what changed: ``... [overridden: lighting day, not night]``.
    A description set by an override itself is left as it is.
    """
    if doc.before_overrides is None or str(doc.marks.get(("description",), ("",))[0]).startswith("--set"):
        return scenario
    before = _condition_values(doc.before_overrides)
    now = _condition_values(scenario.model_dump(mode="json"))
    changed = [f"{name} {now[name]}, not {before[name]}" for name in now if now[name] != before[name]]
    if not changed:
        return scenario
    note = f"[overridden: {'; '.join(changed)}]"
    text = f"{scenario.description} {note}" if scenario.description else note
    return scenario.model_copy(update={"description": text})


def shipped_scenarios() -> list[tuple[str, Path]]:
    """(name, path) of every shipped scenario, base overlays excluded."""
    seen: dict[str, Path] = {}
    for d in scenario_dirs():
        if d.is_dir():
            for p in sorted(d.glob("*.yaml")):
                seen.setdefault(p.stem, p)
    return sorted(seen.items())
