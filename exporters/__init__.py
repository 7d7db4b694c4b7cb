"""``cosim export``: episodes -> other datasets' layouts (docs/exports.md); nothing else lives here.

This folder installs as ``cosim.exporters`` (pyproject.toml ``package-dir``): import it as
``cosim.exporters`` from an installed cosim (``pip install -e .``), never as ``exporters`` or through ``PYTHONPATH=.``.

The package's face imports the built-in formats, which register themselves with
:func:`cosim.exporters.export.register_format`: whoever imports a module of the package finds them all in
``FORMATS``, and ``export.py`` (which the formats import) never imports them back.
"""

from cosim.exporters import airv2x, kitti, opv2v  # noqa: F401 (they register themselves)
