"""The import graph of the source (ast, nothing imported): no package cycle of module-level imports, no import
from a lower layer into a higher one, with the layers of docs/architecture.md ("Layers"), and no circle of
imports between the modules of one package, function-level imports included (a lazy import that closes a
circle hides it, it does not untie it)."""

from __future__ import annotations

import ast
import functools
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
    return list(_imports_in(module, str(path), path.read_text()))


@functools.cache  # the checks below read the same files: each text is parsed once
def _imports_in(module: str, path: str, text: str) -> tuple[tuple[str, bool], ...]:
    tree = ast.parse(text, path)
    package = module if path.endswith("__init__.py") else module.rpartition(".")[0]
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
    return tuple(out)


def module_edges(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules of ``modules`` it imports, at module level or in a function. ``from pkg import
    name`` is an import of ``pkg.name`` when that is a module, else of ``pkg`` (its ``__init__``, where the
    name lives); importing a package's submodule does run the package's ``__init__`` first, but that is
    Python's doing, not an import the code chose: it is no edge. A module importing itself (``python -m``
    entry points) is no edge either."""
    edges: dict[str, set[str]] = defaultdict(set)
    for module, path in modules.items():
        found = imports_of(module, path)
        names = {name for name, _ in found}
        for name, _ in found:
            if name in modules and any(other.startswith(name + ".") and other in modules for other in names):
                continue  # `from pkg import sub`: the import is of pkg.sub (its own entry), not pkg's face
            target = name
            while target not in modules and "." in target:
                target = target.rpartition(".")[0]
            if target in modules and target != module:
                edges[module].add(target)
    return edges


def package_circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The circles of imports between modules of the same package (a package's ``__init__`` counts as one of
    its modules): strongly connected components of the edges that stay inside one package."""
    def package(module: str) -> str:
        return module.rpartition(".")[0]

    inside = {m: {t for t in ts if package(t) == package(m) or t == package(m) or m == package(t)}
              for m, ts in edges.items()}
    return cycles(inside)



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


def upward(every: list[tuple[str, str, str, bool]], layers: dict[str, int]) -> list[str]:
    """The imports of ``every`` (as :func:`package_graph` gives them) from a lower layer into a higher one."""
    return [f"{module} imports {target} ({'module level' if top else 'in a function'}): layer "
            f"{layers[unit_of(module)]} -> {layers[dst]}"
            for module, target, dst, top in every if layers[dst] > layers[unit_of(module)]]


def test_no_import_from_a_lower_layer_into_a_higher_one():
    _, every = package_graph()
    assert upward(every, documented_layers()) == []


def test_no_circle_of_imports_between_the_modules_of_a_package():
    assert package_circles(module_edges(source_modules())) == []


def test_the_checks_catch_a_cycle_and_an_upward_import():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    edges, every = package_graph()
    # the real graph has edges both ways between layers only downwards: io imports world, never back
    assert "cosim.world" in edges["cosim.io"] and "cosim.io" not in edges.get("cosim.world", set())
    assert any(dst == "cosim.actions" and not top for _, _, dst, top in every)  # drones' lazy import is seen


def _toy_package(root: Path, files: dict[str, str]) -> dict[str, Path]:
    """Write ``cosim/toy/<name>.py`` files under ``root``: import name -> file, as :func:`source_modules`."""
    modules = {}
    for name, text in files.items():
        path = root / "cosim" / "toy" / f"{name}.py"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        modules["cosim.toy" if name == "__init__" else f"cosim.toy.{name}"] = path
    return modules


def test_the_checks_catch_a_circle_inside_a_package_and_an_import_up_the_layers(tmp_path):
    files = {"__init__": "from cosim.toy.base import Thing\nfrom cosim.toy import extra\n",
             "base": "Thing = 1\n",
             "extra": "from cosim.toy.base import Thing\n",  # the package's face imports it: no circle
             "a": "import cosim.toy.b\n",
             "b": "def late():\n    from cosim.toy.a import x\n",  # a function-level import closes a circle
             "c": "from cosim.toy import Thing\n",  # a name of the face: an import of cosim/toy/__init__.py
             "d": "import cosim.toy.d\n"}  # itself (a python -m entry point)
    assert package_circles(module_edges(_toy_package(tmp_path, files))) == [["cosim.toy.a", "cosim.toy.b"]]
    files["base"] = "import cosim.toy.c\n"  # base -> c -> the face -> base (and extra, which the face imports)
    assert package_circles(module_edges(_toy_package(tmp_path, files))) == [
        ["cosim.toy", "cosim.toy.base", "cosim.toy.c", "cosim.toy.extra"], ["cosim.toy.a", "cosim.toy.b"]]
    layers = {"cosim.eval": 7, "cosim.batch": 8, "cosim.io": 5}
    every = [("cosim.eval.dataset", "cosim.batch.manifest", "cosim.batch", False),
             ("cosim.batch.runner", "cosim.io.manifest", "cosim.io", True)]
    assert upward(every, layers) == ["cosim.eval.dataset imports cosim.batch.manifest (in a function): layer 7 -> 8"]
