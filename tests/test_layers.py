"""The import graph of the source (ast, nothing imported): no package cycle of module-level imports and no
import from a lower layer into a higher one, with the layers of docs/architecture.md ("Layers")."""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

from tests.helpers import REPO, source_modules

#: Subpackages with a layer of their own (rows of the Layers table below ``cosim.<x>``).
SUBUNITS = ("cosim.sensors.assets",)


def unit_of(module: str) -> str:
    """The package a module belongs to for layering: ``cosim.<x>`` (a subpackage or a top-level module), or one
    of :data:`SUBUNITS`."""
    for sub in SUBUNITS:
        if module == sub or module.startswith(sub + "."):
            return sub
    return ".".join(module.split(".")[:2])


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def imports_of(module: str, path: Path) -> list[tuple[str, bool]]:
    """(imported module or name, at module level) of every cosim import in ``path``; ``from a import b`` gives
    ``a`` and ``a.b`` (b may be a submodule). Imports under ``if TYPE_CHECKING:`` are not run: left out."""
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    skipped = {id(n) for top in ast.walk(tree) if isinstance(top, ast.If) and _is_type_checking(top)
               for n in ast.walk(top)}
    top_level = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            names = [base, *(f"{base}.{a.name}" for a in node.names)]
        else:
            continue
        out += [(n, id(node) in top_level) for n in names if n == "cosim" or n.startswith("cosim.")]
    return out


def documented_layers() -> dict[str, int]:
    """Package -> layer from the table in docs/architecture.md's "Layers" section."""
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text.split("\n## Layers\n", 1)[1].split("\n## ", 1)[0]
    layers = {}
    for row in re.findall(r"^\| (\d+) \| ([^|]+) \|", section, re.M):
        for name in re.findall(r"`([\w.]+)`", row[1]):
            layers[name] = int(row[0])
    return layers


def package_graph() -> tuple[dict[str, set[str]], list[tuple[str, str, str, bool]]]:
    """Module-level edges between packages, and every (importer, imported, package of it, module level)."""
    modules = source_modules()
    edges: dict[str, set[str]] = defaultdict(set)
    every = []
    for module, path in modules.items():
        for target, top in imports_of(module, path):
            src, dst = unit_of(module), unit_of(target)
            if src == dst:
                continue
            every.append((module, target, dst, top))
            if top:
                edges[src].add(dst)
    return edges, every


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(set(edges) | {w for ws in edges.values() for w in ws}):
        if v not in index:
            visit(v)
    return found


def test_every_package_has_a_documented_layer():
    layers = documented_layers()
    units = {unit_of(m) for m in source_modules()}
    assert units - set(layers) == set(), "add these to the Layers table of docs/architecture.md"
    assert set(layers) - units == set(), "the Layers table names packages that do not exist"


def test_no_package_cycle_of_module_level_imports():
    edges, _ = package_graph()
    assert cycles(edges) == []


def test_no_import_from_a_lower_layer_into_a_higher_one():
    layers = documented_layers()
    _, every = package_graph()
    upward = [f"{module} imports {target} ({'module level' if top else 'in a function'}): layer "
              f"{layers[unit_of(module)]} -> {layers[dst]}"
              for module, target, dst, top in every if layers[dst] > layers[unit_of(module)]]
    assert upward == []


def test_the_checks_catch_a_cycle_and_an_upward_import():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    edges, every = package_graph()
    # the real graph has edges both ways between layers only downwards: io imports world, never back
    assert "cosim.world" in edges["cosim.io"] and "cosim.io" not in edges.get("cosim.world", set())
    assert any(dst == "cosim.actions" and not top for _, _, dst, top in every)  # drones' lazy import is seen
