"""The wheel must carry every package, including the top-level sensors/ and exporters/ folders."""

from __future__ import annotations

import tomllib

from tests.conftest import REPO

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
