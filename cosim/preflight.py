"""What a run needs besides a valid scenario, checked before any work: by the run itself and, with the same
messages, by ``cosim run --dry-run`` and ``cosim batch --dry-run`` (which build and run nothing).

Light on purpose (no engine is imported): a missing package is found with ``importlib.util.find_spec``.
"""

from __future__ import annotations

import importlib.util
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from cosim.errors import InputError
from cosim.scenario.loader import LoadedScenario, printable

#: The first bytes a map file of each kind must hold (within its first 4 KiB).
MAP_FILE_MARKERS = {"net": (b"<net", "a SUMO network (.net.xml): no <net> element at its start"),
                    "osm": (b"<osm", "an OpenStreetMap XML file: no <osm> element at its start")}
#: pip package of each dynamics backend (both are dependencies of cosim; a trimmed install may lack one).
BACKEND_PACKAGES = {"jsbsim": "jsbsim", "pybullet": "pybullet"}
RAY_MISSING = "--backend ray needs Ray: pip install -e '.[ray]' (or pip install 'ray>=2.9')"


def map_file(loaded: LoadedScenario) -> Path | None:
    """The scenario's map file (kinds net and osm), resolved against the scenario's folder and checked to
    exist and hold its kind's XML; None for generated maps."""
    spec = loaded.scenario.map
    return check_map(spec.kind, spec.file, loaded.base_dir)


def check_map(kind: str, file: str | None, base_dir: Path) -> Path | None:
    """See :func:`map_file`; ``file`` relative to ``base_dir``."""
    if kind not in MAP_FILE_MARKERS:
        return None
    path = Path(file or "")
    path = path if path.is_absolute() else (Path(base_dir) / path).resolve()
    shown = printable(file or "")
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except FileNotFoundError:
        raise InputError(f"map.file {shown!r} not found (looked at {printable(str(path))})") from None
    except OSError as exc:
        raise InputError(f"map.file {shown!r}: cannot read {printable(str(path))}: {exc.strerror}") from None
    marker, what = MAP_FILE_MARKERS[kind]
    if marker not in head:
        raise InputError(f"map.file {printable(str(path))} is not {what}")
    return path


def check_backends(backends: set[str], where: str = "the drones") -> None:
    """The dynamics backends' packages are installed."""
    for backend in sorted(backends):
        if importlib.util.find_spec(BACKEND_PACKAGES[backend]) is None:
            raise InputError(f"{where} fly with the {backend} backend, which is not installed: "
                             f"pip install {BACKEND_PACKAGES[backend]}")


def check_scenario_inputs(loaded: LoadedScenario) -> None:
    """Everything an episode of ``loaded`` needs that the schema cannot check: its map file and the packages
    of its drones' dynamics backends."""
    map_file(loaded)
    agents = loaded.scenario.agents
    check_backends({agents.drone_backend_of(i) for i in range(len(agents.drones))})


def check_plan_inputs(episodes: Iterable[Any]) -> None:
    """:func:`check_scenario_inputs` for every planned episode of a batch (``cosim.batch.plan.Episode``: its
    resolved scenario data and folder), each distinct map once."""
    maps: set[tuple[str, str | None, str]] = set()
    backends: set[str] = set()
    for ep in episodes:
        spec = ep.scenario.get("map") or {}
        maps.add((spec.get("kind", "urban"), spec.get("file"), ep.base_dir))
        agents = ep.scenario.get("agents") or {}
        backends.update(d.get("backend") or agents.get("drone_backend", "jsbsim") for d in agents.get("drones") or [])
    for kind, file, base_dir in sorted(maps, key=str):
        check_map(kind, file, Path(base_dir))
    check_backends(backends & set(BACKEND_PACKAGES), "drones of the sweep")


def check_ray_installed() -> None:
    """``--backend ray`` needs the ``ray`` extra."""
    if importlib.util.find_spec("ray") is None:
        raise InputError(RAY_MISSING)


def check_output_dir(out_dir: Path, *, create: bool = True) -> None:
    """Make sure episodes can be written into ``out_dir`` (created if missing) before any work is done.

    Raises :class:`~cosim.errors.InputError` naming the folder for a path that is a file, lies under a file,
    cannot be created or is not writable (read-only file system, no permission, ``/proc``). ``create=False``
    (dry runs) creates nothing: a missing folder's nearest existing parent must be a writable folder.
    """
    out = probe = Path(out_dir)
    try:
        if "\0" in str(out):
            raise ValueError("a path cannot hold a NUL character")
        if out.exists() and not out.is_dir():
            raise InputError(f"output folder {printable(str(out))} is a file, not a folder")
        if create:
            out.mkdir(parents=True, exist_ok=True)
        else:
            while not probe.exists() and probe.parent != probe:
                probe = probe.parent
            if not probe.is_dir():
                raise InputError(f"cannot write episodes into output folder {printable(str(out))}: "
                                 f"{printable(str(probe))} is a file, not a folder")
        with tempfile.NamedTemporaryFile(dir=probe, prefix=".cosim-write-check-"):
            pass
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc)
        where = printable(str(out)) + ("" if probe == out else f" (in {printable(str(probe))})")
        raise InputError(f"cannot write episodes into output folder {where}: {reason}") from None
