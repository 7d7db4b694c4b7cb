"""Shared fixtures of the suite (shared helper functions: tests/helpers.py), and how it runs on several cores.

``make test`` runs the suite on pytest-xdist workers with ``--dist loadgroup``. Before that can be safe and
cheap, :func:`pytest_collection_modifyitems` gives each test an ``xdist_group``, so that tests which share a
module- or session-scoped fixture (an episode generated once, the smoke batch) run on one worker (the fixture
is built once, not once per worker), and so do tests marked ``resource(NAME)`` with the same name (a thing
two of them must not use at once); then it orders the units xdist hands out. :func:`pytest_runtest_protocol`
holds the suite lock around every test: tests marked ``exclusive`` (timing deadlines) run beside no heavy
test and at most one light one, and heavy ones wait for the numba kernels compiled in the controlling process
(tests/scheduling.py says how and why).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from tests import scheduling
from tests.helpers import REPO, load_factor, run_cli

#: ``make test-fast`` sets this: the lane of unit tests (``-m "not integration ..."``) must start no engine.
FAST_LANE = os.environ.get("COSIM_TEST_FAST") == "1"
_ENGINE_SUBCOMMANDS = {"run"}


def _refuse(what: str):
    def refuse(*_args, **_kwargs):
        raise RuntimeError(f"{what} in the fast lane (make test-fast): mark this test @pytest.mark.integration")

    return refuse


def _starts_an_episode(args) -> bool:
    """``cosim run ...`` (as a console script or ``python -m cosim.cli``)."""
    argv = [str(a) for a in ([args] if isinstance(args, str | os.PathLike) else list(args))]
    for i, a in enumerate(argv):
        if (a == "cosim.cli" or a.endswith("/cosim") or a == "cosim") and i + 1 < len(argv):
            return bool(_ENGINE_SUBCOMMANDS & set(argv[i + 1:i + 2]))
    return False


@pytest.fixture(scope="session", autouse=True)
def _fast_lane_guard():
    """In the fast lane, starting SUMO, JSBSim, PyBullet or a `cosim run` process fails the test
    with a message saying to mark it ``integration``: the lane stays a lane of unit tests."""
    if not FAST_LANE:
        yield
        return
    import jsbsim
    import libsumo
    import pybullet

    popen_init = subprocess.Popen.__init__

    def guarded_popen(self, args, *rest, **kwargs):
        if _starts_an_episode(args):
            _refuse(f"`{' '.join(map(str, args))}`")()
        popen_init(self, args, *rest, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(libsumo, "start", _refuse("SUMO (libsumo.start)"))
        mp.setattr(jsbsim, "FGFDMExec", _refuse("JSBSim"))
        mp.setattr(pybullet, "connect", _refuse("PyBullet"))
        mp.setattr(subprocess.Popen, "__init__", guarded_popen)
        yield


@pytest.fixture
def tiny_overrides() -> list[str]:
    """Overrides that make any shipped scenario small and fast: short, no sensors, small map."""
    return ["duration_s=2", "sensors.enabled=false", "map.size_m=300", "traffic.density_veh_per_km=6"]


@pytest.fixture
def no_world(monkeypatch):
    """Fail if a command gets as far as building the world (its input checks must come first)."""
    import cosim.world

    def refuse(*_a, **_k):
        raise AssertionError("the world was built before the input was checked")

    monkeypatch.setattr(cosim.world, "build_world", refuse)


@pytest.fixture(scope="session")
def synthetic_episodes(tmp_path_factory) -> list[Path]:
    """Two small synthetic episodes with sensors (visibility included), of 2 and 3 ticks (episode ids ``syn`` and
    ``syn_3_ticks``; :func:`cosim.io.synthetic.write_synthetic_episode`, no engines). Read them, never write them."""
    from cosim.io.synthetic import write_synthetic_episode

    d = tmp_path_factory.mktemp("synthetic")
    return [write_synthetic_episode(d / "syn.mcap", ticks=2, sensors=True),
            write_synthetic_episode(d / "syn_3_ticks.mcap", ticks=3, sensors=True)]


@pytest.fixture(scope="session")
def synthetic_episode(synthetic_episodes) -> Path:
    """The first of :func:`synthetic_episodes` (2 ticks, a vehicle, an RSU and a drone with sensors)."""
    return synthetic_episodes[0]


@pytest.fixture(scope="session")
def smoke_batch(tmp_path_factory) -> Path:
    """One local batch of ``sweeps/smoke.yaml`` (6 tiny episodes, 2 workers): the reference every other way of
    running that sweep (resumed, Ray, a Ray cluster, shard containers) must reproduce. Read it, never write it."""
    out = tmp_path_factory.mktemp("smoke-batch") / "ref"
    r = run_cli("batch", str(REPO / "sweeps" / "smoke.yaml"), "--out", str(out), "--workers", "2", timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "6 generated, 0 failed" in r.stdout
    return out


@pytest.fixture(scope="session")
def export_episode(tmp_path_factory) -> Path:
    """A short full-rig episode (5 vehicles, 5 RSUs, 5 drones) at quarter image size, LiDAR noise off, the
    vehicles' and RSUs' LiDARs off their agent's vertical axis (so composing poses as transforms instead of
    component by component would misplace them). The exports' tests (tests/test_export*.py) read it."""
    import yaml

    from cosim.scenario import load_scenario

    d = tmp_path_factory.mktemp("export_episode")
    sc = load_scenario("default", ["duration_s=1", "sensors.image_scale=0.25", "map.size_m=300",
                               "output.image_format=jpeg"]).scenario  # exports from a JPEG episode
    doc = sc.model_dump(mode="json")
    for kind in ("vehicle", "rsu", "drone"):
        doc["sensors"][kind]["lidar"]["range_noise_m"] = 0.0
        # A sweep's points smear over its period when agents move (motion distortion); these geometric checks
        # compare points with boxes at the tick time, so they use instantaneous sweeps.
        doc["sensors"][kind]["lidar"]["motion_distortion"] = False
    doc["sensors"]["vehicle"]["lidar"]["mount"]["xyz_m"] = [1.0, 0.4, 1.9]
    doc["sensors"]["rsu"]["lidar"]["mount"]["xyz_m"] = [0.6, -0.5, 0.3]
    (d / "scenario.yaml").write_text(yaml.safe_dump(doc))
    r = run_cli("run", str(d / "scenario.yaml"), "--out", str(d), "-q")
    assert r.returncode == 0, r.stderr
    return next(d.glob("*.mcap"))


@pytest.fixture(scope="session")
def smeared_episode(tmp_path_factory) -> Path:
    """An episode with the default LiDARs (motion distortion on): two connected vehicles among parked cars,
    an RSU and an escort drone just started; small camera images."""
    d = tmp_path_factory.mktemp("smeared_episode")
    r = run_cli("run", "town_urban_day_clear", "--out", str(d), "-q", "--duration", "1",
                "--set", "sensors.image_scale=0.05", "--set", "map.size_m=300", "--set", "agents.vehicles.count=2",
                "--set", "agents.rsus.count=1", "--set", "parked.density_veh_per_km=60",
                "--set", "pedestrians.density_per_km=0",
                "--set", 'agents.drones=[{strategy: escort, target: vehicle_0, altitude_m: 40, offset_m: [-8, 0]}]')
    assert r.returncode == 0, r.stderr
    return next(d.glob("*.mcap"))


# ------------------------------------------------------------------------------ running on xdist workers


def _shared_fixtures(item: pytest.Item) -> set[str]:
    """``where::name`` of every module-, package- or session-scoped fixture of this suite that the test uses,
    directly or through other fixtures (autouse ones it does not ask for are left out: they are cheap)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return set()
    found, todo, seen = set(), list(info.argnames), set()
    while todo:
        name = todo.pop()
        if name in seen or name not in info.name2fixturedefs:
            continue
        seen.add(name)
        fixturedef = info.name2fixturedefs[name][-1]
        todo.extend(fixturedef.argnames)
        if fixturedef.scope != "function" and fixturedef.baseid.startswith("tests"):
            found.add(f"{fixturedef.baseid}::{name}")  # no "@": xdist splits a group name off at the last one
    return found


_WARM_UP = scheduling.KernelWarmUp()


def _run_folder(config: pytest.Config) -> Path:
    """The run's temporary folder, which its workers share (each worker's own is a folder in it)."""
    base = config._tmp_path_factory.getbasetemp()
    return base.parent if hasattr(config, "workerinput") else base


def _controls_workers(config: pytest.Config) -> bool:
    return config.pluginmanager.hasplugin("dsession")  # xdist's controlling process (-n N, N >= 1)


def pytest_configure(config: pytest.Config) -> None:
    """xdist hands the units out in the order :func:`pytest_collection_modifyitems` leaves them in (its default
    sorts them by their number of tests). Set in every process: xdist's controller is not registered yet here
    (its own ``pytest_configure`` runs last), and the option means nothing elsewhere."""
    config.option.loadscopereorder = False


@pytest.hookimpl(tryfirst=True)  # before xdist starts the workers (its hook is trylast)
def pytest_sessionstart(session: pytest.Session) -> None:
    """The numba kernels compiled once (tests/warm_kernels.py): in the background while xdist's workers start
    and run light tests, else before the first test; not in the fast lane, which starts no episode, nor in a
    worker, which makes its own compilations wait for the controller's instead."""
    config = session.config
    if FAST_LANE:
        return
    if hasattr(config, "workerinput"):
        _WARM_UP.hold_compilations(_run_folder(config))
        return
    from tests.warm_kernels import kernels_cached, warm_kernels

    if kernels_cached():
        _WARM_UP.line = "numba kernels: cached"
    elif _controls_workers(config):
        _WARM_UP.start(_run_folder(config), warm_kernels)
    else:
        _WARM_UP.line = warm_kernels()


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    if line := _WARM_UP.join():
        terminalreporter.write_line(line)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """One ``xdist_group`` per set of tests linked by a shared fixture or a ``resource`` mark (union-find);
    a test linked to none stays free: xdist's loadgroup hands it to whichever worker is idle. On a worker, the
    units (a group, or a free test) in :func:`tests.scheduling.order_units`'s order, which xdist keeps."""
    if not config.pluginmanager.hasplugin("xdist"):  # -p no:xdist: no such mark to give
        return
    parent: dict[str, str] = {}

    def find(key: str) -> str:
        while parent.setdefault(key, key) != key:
            parent[key] = parent[parent[key]]
            key = parent[key]
        return key

    keys = {}
    for item in items:
        own = _shared_fixtures(item) | {f"resource:{m.args[0]}" for m in item.iter_markers("resource")}
        if item.get_closest_marker("exclusive"):  # one after the other on one worker: the lock is taken once
            own.add("resource:exclusive")
        keys[item] = sorted(own)
        for other in keys[item][1:]:
            parent[find(other)] = find(keys[item][0])
    units: dict[str, list[pytest.Item]] = {}
    for item in items:
        if keys[item]:
            item.add_marker(pytest.mark.xdist_group(find(keys[item][0])))
        units.setdefault(find(keys[item][0]) if keys[item] else item.nodeid, []).append(item)
    if not hasattr(config, "workerinput"):  # one process (-n 0): the tests in their files' order
        return
    order = scheduling.order_units([
        scheduling.Unit(key, _unit_kind(tests), sum(scheduling.cost_of(_marks(t)) for t in tests))
        for key, tests in units.items()])
    items[:] = [item for unit in order for item in units[unit.key]]


def _marks(item: pytest.Item) -> set[str]:
    return {m.name for m in item.iter_markers()}


def _unit_kind(tests: list[pytest.Item]) -> str:
    kinds = {scheduling.kind_of(_marks(t)) for t in tests}
    return next(k for k in (scheduling.EXCLUSIVE, scheduling.HEAVY, scheduling.LIGHT) if k in kinds)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Fail the run when xdist's loadgroup did not take the groups (it appends ``@group`` to the node id, which
    pytest 9.2 ignores: pytest-xdist issue 1386): shared fixtures would be built twice and Ray started twice."""
    if not getattr(session.config.option, "loadgroup", False):
        return
    grouped = [item for item in session.items if item.get_closest_marker("xdist_group")]
    if grouped and "@" not in grouped[0].nodeid:
        raise pytest.UsageError(f"--dist loadgroup ignores the xdist_group marks with pytest {pytest.__version__} "
                                "(pytest-xdist issue 1386): install the test extra's pytest (pyproject.toml)")


_SUITE_LOCK: scheduling.SuiteLock | None = None


def _timeout_for_the_load(item: pytest.Item) -> None:
    """pytest-timeout's limit of ``item`` (its ``timeout`` marker, else ``--timeout`` / the ini's), times the
    machine's load factor now (:func:`tests.helpers.load_factor`): a limit that fits a quiet machine fits a
    busy one too, where fixtures that build worlds and episodes take several times as long."""
    marker = item.get_closest_marker("timeout")
    if marker is not None:
        base = marker.args[0] if marker.args else marker.kwargs.get("timeout")
    else:
        base = item.config.getoption("timeout", None) or item.config.getini("timeout")
    try:
        base = float(base)
    except (TypeError, ValueError):
        return
    factor = load_factor()
    if base > 0 and factor > 1:
        kwargs = dict(marker.kwargs) if marker is not None else {}
        kwargs.pop("timeout", None)
        item.add_marker(pytest.mark.timeout(round(base * factor), *(marker.args[1:] if marker else ()), **kwargs),
                        append=False)


@pytest.hookimpl(wrapper=True, tryfirst=True)  # outside pytest-timeout's wrapper: its timer starts after this
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    """On an xdist worker, each test (its fixtures' set-up and teardown included) runs under the suite lock
    (tests/scheduling.py), a heavy or exclusive one once the numba kernels are compiled; everywhere, its time
    limit scales with the machine's load (:func:`_timeout_for_the_load`)."""
    global _SUITE_LOCK
    _timeout_for_the_load(item)
    if not hasattr(item.config, "workerinput"):
        return (yield)
    folder = _run_folder(item.config)
    kind = scheduling.kind_of(_marks(item))
    if kind != scheduling.LIGHT:
        _WARM_UP.wait(folder)
    _SUITE_LOCK = _SUITE_LOCK or scheduling.SuiteLock(folder)
    leave = _SUITE_LOCK.enter(kind, scheduling.kind_of(_marks(nextitem)) if nextitem is not None else None)
    try:
        return (yield)
    finally:
        leave()
