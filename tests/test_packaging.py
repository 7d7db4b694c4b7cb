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


def _data_dirs() -> set[str]:
    """Folders of package data (cosim/data/...) that hold files: setuptools wants them listed as packages."""
    return {".".join(f.parent.relative_to(REPO).parts) for f in (REPO / "cosim" / "data").rglob("*") if f.is_file()}


def test_every_package_is_listed_for_the_wheel():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert set(config["packages"]) == _package_dirs() | _data_dirs()
    assert {k: v for k, v in config["package-dir"].items() if k in MAPPED} == MAPPED
    assert all(d in config["package-data"] for d in _data_dirs())


def test_building_the_package_prints_no_setuptools_warning(tmp_path):
    """`make run` installs with pip install -e .: no deprecation or package-data blocks from setuptools."""
    import shutil
    import subprocess
    import sys

    src = tmp_path / "src"  # a copy: building in place would leave build/ in the checkout
    for name in ("cosim", "sensors", "exporters"):
        shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--wheel-dir", str(tmp_path), str(src)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    text = r.stdout + r.stderr
    assert "BuildBackendWarning" not in text and "SetuptoolsDeprecationWarning" not in text, text[-3000:]
    import zipfile

    (wheel,) = tmp_path.glob("cosim-*.whl")
    assert "cosim/data/jsbsim/aircraft/cosim_quad/cosim_quad.xml" in zipfile.ZipFile(wheel).namelist()


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
