"""``cosim export``: episodes -> other datasets' layouts (docs/exports.md); nothing else lives here.

This folder installs as ``cosim.exporters`` (pyproject.toml ``package-dir``): import it as
``cosim.exporters`` from an installed cosim (``pip install -e .``), never as ``exporters`` or through ``PYTHONPATH=.``.
"""
