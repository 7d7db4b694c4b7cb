"""The wheel must carry every package, including the top-level sensors/ and exporters/ folders."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

from tests.helpers import REPO, source_modules

MAPPED = {"cosim.sensors": "sensors", "cosim.exporters": "exporters"}


def _package_dirs() -> set[str]:
    found = set()
    for init in REPO.glob("cosim/**/__init__.py"):
        found.add(".".join(init.parent.relative_to(REPO).parts))
    for name, folder in MAPPED.items():
        for init in (REPO / folder).glob("**/__init__.py"):
            found.add(".".join([name, *init.parent.relative_to(REPO / folder).parts]))
    return found


def test_every_package_is_listed_for_the_wheel():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert set(config["packages"]) == _package_dirs()
    assert {k: v for k, v in config["package-dir"].items() if k in MAPPED} == MAPPED


def test_no_generic_top_level_import_names():
    import cosim.exporters
    import cosim.sensors

    assert cosim.sensors.__name__ == "cosim.sensors" and cosim.exporters.__name__ == "cosim.exporters"


_IMPORT_ALL = """
import importlib, json, sys
print(json.dumps({name: importlib.import_module(name).__file__ for name in sys.argv[1:]}))
"""


def test_every_module_imports_through_the_installed_package(tmp_path):
    """From a plain checkout, every module of cosim/, sensors/ and exporters/ imports by its installed name
    (the editable install's package-dir mapping), in a fresh interpreter started outside the checkout, and
    resolves to its file in this checkout."""
    modules = source_modules()
    assert {"cosim.io.writer", "cosim.sensors.gnss", "cosim.exporters.export"} <= set(modules)
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "MPLBACKEND": "Agg"}
    r = subprocess.run([sys.executable, "-c", _IMPORT_ALL, *sorted(modules)], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    files = json.loads(r.stdout.splitlines()[-1])
    assert {name: Path(f).resolve() for name, f in files.items()} == {n: p.resolve() for n, p in modules.items()}
