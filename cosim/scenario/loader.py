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
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from cosim.errors import ScenarioError
from cosim.scenario.merge import merge_fields
from cosim.scenario.model import (
    DRONE_STRATEGIES,
    EVENT_KINDS,
    EnvironmentSpec,
    MapSpec,
    RuleError,
    Scenario,
    WrongKind,
    complete_rigs,
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


#: A plain scalar such as ``1e9`` or ``1.2E-3``: a float in YAML 1.2, text in PyYAML's YAML 1.1.
_YAML12_EXPONENT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)[eE][-+]?[0-9]+")


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
    if node.tag == "tag:yaml.org,2002:str" and node.style is None and _YAML12_EXPONENT.fullmatch(node.value):
        return float(node.value)  # YAML 1.2 reads a plain 1e9 as a number; PyYAML (YAML 1.1) as text
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
    """Parse a scenario file with its ``extends:`` chain merged in, rigs but their LiDARs completed
    (:func:`complete_rigs`: a LiDAR ``model`` is expanded at validation, after any ``--set``)."""
    doc = _load_with_extends(path, ())
    doc.data["sensors"] = complete_rigs(doc.data.get("sensors", {}), lidar=False)
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
    src, line = doc.marks[("extends",)]
    if not isinstance(parent, str):
        raise ScenarioError("extends must be a path to a scenario file or the name of a shipped one",
                            path="extends", line=line, source=src)
    base_path = _find_base(parent, path.parent, line, src)
    base = _load_with_extends(base_path, (*seen, path))
    marks = dict(base.marks)
    marks.update(doc.marks)
    return YamlDoc(merge_fields(base.data, doc.data), marks)


def _find_base(parent: str, folder: Path, line: int | None, source: str) -> Path:
    """The file ``extends: parent`` names: a path relative to the extending file's ``folder``, else a shipped
    scenario by name (``default``, ``base/paper``) from anywhere; a misspelt name gets a did-you-mean."""
    folders = [folder] if Path(parent).is_absolute() else [folder, *scenario_dirs()]
    try:
        if "\0" in parent:
            raise ValueError("a file name cannot hold a NUL character")
        for d in folders:
            for cand in (d / parent, d / f"{parent}.yaml"):
                if cand.is_file():
                    return cand.resolve()
    except (OSError, ValueError) as exc:  # a name too long for the file system, a NUL in it
        raise ScenarioError(f"cannot open the base scenario {printable(parent, 80)!r}: "
                            f"{getattr(exc, 'strerror', None) or exc}", path="extends", line=line,
                            source=source) from None
    raise ScenarioError(f"base scenario not found: {printable(parent, 80)!r} is neither a file beside "
                        f"{source or 'the scenario'} nor a shipped scenario{_did_you_mean(parent)}",
                        path="extends", line=line, source=source)


def _shipped_names() -> list[str]:
    """Names of every shipped scenario, base overlays included (``default``, ``base/paper``)."""
    names: set[str] = set()
    for d in scenario_dirs():
        if d.is_dir():
            names.update(p.relative_to(d).with_suffix("").as_posix() for p in d.rglob("*.yaml"))
    return sorted(names)


def _did_you_mean(name: str | Path) -> str:
    """``; did you mean 'town_rural_night'?`` for a name close to a shipped scenario's, else ``""``."""
    text = str(name)
    stem = text[:-5] if text.endswith((".yaml", ".YAML")) else text
    close = difflib.get_close_matches(stem, _shipped_names(), n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def apply_override(doc: YamlDoc, assignment: str) -> None:
    """Apply one ``a.b.0.c=value`` override; the value is parsed as YAML (``3``, ``true``, ``[1, 2]``)."""
    key, sep, raw = assignment.partition("=")
    source = f"--set {printable(assignment)}"
    if not sep or not key.strip():
        raise ScenarioError("expected KEY=VALUE, for example --set environment.weather=foggy", source=source)
    parts: list[str | int] = [int(p) if p.isdigit() else p for p in key.strip().split(".")]
    if _deeper_than(raw, MAX_FLOW_DEPTH) is not None:
        raise ScenarioError(f"value is not valid YAML: brackets nested more than {MAX_FLOW_DEPTH} levels deep",
                            path=printable(key), source=source)
    try:
        node = yaml.compose(raw, Loader=_LineLoader) if raw.strip() else None
        value = _construct(node, source, tuple(parts), {}) if node is not None else None if raw.strip() else ""
    except yaml.reader.ReaderError as exc:
        raise ScenarioError(f"value is not valid YAML: control character U+{int(exc.character):04X} is not allowed",
                            path=printable(key), source=source) from None
    except yaml.MarkedYAMLError as exc:
        raise ScenarioError(f"value is not valid YAML: {exc.problem}", path=printable(key), source=source) from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"value is not valid YAML: {exc}", path=printable(key), source=source) from None
    except RecursionError:
        raise ScenarioError("value is nested too deeply", path=printable(key), source=source) from None
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


def printable(text: str, limit: int = 120) -> str:
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

    drone_of = {"hover": m.HoverDrone, "patrol": m.PatrolDrone, "escort": m.EscortDrone}
    cls: Any = Scenario
    node = data
    items: Any = None  # the model of the values of a mapping field (``rigs``): the next part is a key
    for part in path:
        if isinstance(part, int):
            node = node[part] if isinstance(node, list) and part < len(node) else None
            if items == "drones":
                cls = drone_of.get(node.get("strategy", "hover")) if isinstance(node, dict) else None
            items = None
            continue
        node = node.get(part) if isinstance(node, dict) else None
        if items is not None:
            cls, items = items, None
            continue
        if not (isinstance(cls, type) and issubclass(cls, BaseModel)) or part not in cls.model_fields:
            return None
        ann = cls.model_fields[part].annotation
        if part == "drones":
            cls, items = None, "drones"
            continue
        cls = ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None
        if cls is None and ann is not None:
            for arg in getattr(ann, "__args__", ()):
                if isinstance(arg, type) and issubclass(arg, BaseModel):
                    cls = arg
            if getattr(ann, "__origin__", None) is dict:
                cls, items = None, cls
    if cls is None and isinstance(node, dict) and "strategy" in node:
        cls = drone_of.get(node["strategy"])
    if cls is None and len(path) >= 2 and path[-2] == "drones" and isinstance(node, dict):
        cls = drone_of.get(node.get("strategy", "hover"))
    return cls


def unknown_key_message(bad: str, owner: type[BaseModel] | None) -> str:
    """``unknown key 'wether'; did you mean 'weather'? (known keys: ...)`` for the model that owns the mapping."""
    if owner is None:
        return f"unknown key {bad!r}"
    known = list(owner.model_fields)
    close = difflib.get_close_matches(bad, known, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown key {bad!r}{hint} (known keys: {', '.join(known)})"


#: Longest rendering of an offending value inside an error message [characters].
MAX_VALUE_CHARS = 80
#: Longest message of one problem [characters].
MAX_MESSAGE_CHARS = 400
#: Most problems listed for one invalid file (the rest are counted).
MAX_PROBLEMS = 10


def shown_value(value: Any) -> str:
    """A bad value as JSON for an error message, cut to :data:`MAX_VALUE_CHARS`."""
    return printable(json.dumps(value, default=str), MAX_VALUE_CHARS)


def error_message(err: dict[str, Any], path: list[str | int], data: Any) -> str:
    kind = err["type"]
    if isinstance(err.get("input"), WrongKind):
        return err["input"].message
    if kind == "extra_forbidden":
        return unknown_key_message(printable(str(path[-1]), MAX_VALUE_CHARS), _model_at(path[:-1], data))
    if kind == "missing":
        return "required key is missing"
    if kind in ("literal_error", "enum"):
        return f"{err['msg']}, got {shown_value(err.get('input'))}"
    if kind == "union_tag_invalid":
        key = str(err["ctx"].get("discriminator", "'strategy'")).strip("'")
        return (f"unknown {key} {printable(repr(err['ctx']['tag']), MAX_VALUE_CHARS)}; "
                f"expected one of {err['ctx']['expected_tags']}")
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    got = err.get("input")
    if kind not in ("value_error", "assertion_error") and not isinstance(got, dict | list):
        msg += f", got {shown_value(got)}"
    return printable(msg, MAX_MESSAGE_CHARS)  # a rule's own message may quote a long value in full


def _override_marks(doc: YamlDoc) -> list[tuple[Key, tuple[str, int | None]]]:
    """(key path, mark) of every ``--set`` applied to ``doc``, in order."""
    return [(k, m) for k, m in doc.marks.items() if str(m[0]).startswith("--set ")]


def _where(path: Sequence[str | int], doc: YamlDoc, from_file: bool | None) -> tuple[str, int | None]:
    """The (source, line) to name for a problem at ``path``: its own mark, else the nearest marked parent's; a
    ``--set`` when one caused it. ``from_file``: whether the problem is there without the overrides (None:
    not known). Without its own mark a problem that an override caused names that override (the one sharing
    most of the path, else the last), never the file's first line."""
    depth, mark = 0, ("", None)
    for n in range(len(path), -1, -1):
        found = doc.marks.get(tuple(path[:n]))
        if found is not None:
            depth, mark = n, found
            break
    overrides = _override_marks(doc)
    if not overrides or str(mark[0]).startswith("--set ") or from_file:
        return mark
    shared = [(_shared(k, path), m) for k, m in overrides]
    best_len = max(n for n, _ in shared)
    best = [m for n, m in shared if n == best_len][-1]
    if from_file is False or depth == 0 or (depth < len(path) and best_len >= depth):
        return best
    return mark


def _shared(a: Sequence[Any], b: Sequence[Any]) -> int:
    """How many leading parts two key paths share."""
    n = 0
    for x, y in zip(a, b, strict=False):
        if x != y:
            break
        n += 1
    return n


def located_error(
    exc: ValidationError,
    doc: YamlDoc,
    *,
    error_cls: type[ScenarioError] = ScenarioError,
    clean: Callable[[Sequence[str | int], Any], list[str | int]] = clean_error_loc,
    message: Callable[[dict[str, Any], list[str | int], Any], str] = error_message,
    without_overrides: set[str] | None = None,
) -> ScenarioError:
    """One error for a failed validation listing its problems (up to :data:`MAX_PROBLEMS`), each with its
    dotted key path and the file and line it was written at, or the ``--set`` that caused it (``clean`` and
    ``message`` let other YAML formats, such as sweeps, adapt both). ``without_overrides``: the key paths
    that fail without the overrides too (None: not known)."""
    problems: list[ScenarioError] = []
    seen: set[str] = set()
    for err in exc.errors(include_url=False):
        path = clean(err["loc"], doc.data)
        ctx_error = (err.get("ctx") or {}).get("error")
        if isinstance(ctx_error, RuleError):
            path = path + [int(p) if p.isdigit() else p for p in ctx_error.path.split(".")]
        key = dotted(path)
        if key in seen:  # one problem per key (a union reports each of its members)
            continue
        seen.add(key)
        from_file = None if without_overrides is None else key in without_overrides
        source, line = _where(path, doc, from_file)
        problems.append(error_cls(message(err, path, doc.data), path=printable(key), line=line, source=source))
    if len(problems) == 1:
        return problems[0]
    order = {p.source: i for i, p in reversed(list(enumerate(problems)))}
    problems.sort(key=lambda p: (order[p.source], p.line is None, p.line or 0))
    first = problems[0]
    return error_cls(f"{len(problems)} problems", path=first.path, line=first.line, source=first.source,
                     problems=problems[:MAX_PROBLEMS], more=max(0, len(problems) - MAX_PROBLEMS))


def failing_keys(exc: ValidationError, data: Any) -> set[str]:
    """Dotted key paths of every problem of a failed validation (as :func:`located_error` names them)."""
    out = set()
    for err in exc.errors(include_url=False):
        path = clean_error_loc(err["loc"], data)
        ctx_error = (err.get("ctx") or {}).get("error")
        if isinstance(ctx_error, RuleError):
            path = path + [int(p) if p.isdigit() else p for p in ctx_error.path.split(".")]
        out.add(dotted(path))
    return out


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
    shown = printable(str(name_or_path), 120)
    raise ScenarioError(f"scenario not found: {shown}{_did_you_mean(name_or_path)} (see `cosim scenarios` for "
                        "the shipped ones)", source=shown)


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
        raise located_error(exc, doc, without_overrides=_failing_without_overrides(doc)) from None
    scenario = describe_overridden_conditions(scenario, doc)
    resolved = scenario.model_dump(mode="json")
    return LoadedScenario(scenario, file, resolved, file.parent if file else Path.cwd())


def _failing_without_overrides(doc: YamlDoc) -> set[str] | None:
    """Key paths that fail validation before any ``--set`` was applied (None: there were no overrides)."""
    if doc.before_overrides is None:
        return None
    try:
        Scenario.model_validate(doc.before_overrides)
    except ValidationError as exc:
        return failing_keys(exc, doc.before_overrides)
    return set()


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
