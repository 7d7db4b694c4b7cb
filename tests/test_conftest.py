"""The suite's own machinery (tests/conftest.py, tests/helpers.py): time limits and wall-clock bounds that scale
with the measured load.
"""

from __future__ import annotations

import pytest

# ------------------------------------------------------------------------------ time limits on a busy machine


class _Item:
    """What :func:`tests.conftest._timeout_for_the_load` uses of a pytest item."""

    def __init__(self, marker=None, ini="300"):
        self.markers = [marker] if marker is not None else []
        self.config = type("Config", (), {"getoption": lambda self, name, default=None: None,
                                          "getini": lambda self, name: ini})()

    def get_closest_marker(self, name):
        return self.markers[0] if self.markers else None

    def add_marker(self, marker, append=True):
        self.markers.insert(0 if not append else len(self.markers), marker.mark)


def test_time_limits_scale_with_the_measured_load(monkeypatch):
    """At load 12 on 2 cores every test's limit (its marker's, else the ini's 300 s) is 6 times as long;
    on a quiet machine it stays as written."""
    import tests.conftest as conftest

    monkeypatch.setattr(conftest, "load_factor", lambda: 6.0)
    item = _Item()
    conftest._timeout_for_the_load(item)
    assert item.get_closest_marker("timeout").args == (1800,)
    item = _Item(pytest.mark.timeout(900, method="thread").mark)
    conftest._timeout_for_the_load(item)
    assert item.get_closest_marker("timeout").args == (5400,)
    assert item.get_closest_marker("timeout").kwargs == {"method": "thread"}
    monkeypatch.setattr(conftest, "load_factor", lambda: 1.0)
    item = _Item(pytest.mark.timeout(900).mark)
    conftest._timeout_for_the_load(item)
    assert item.get_closest_marker("timeout").args == (900,)


def test_load_bound_scales_a_deadline_by_load_over_cores(monkeypatch):
    import os

    from tests.helpers import load_bound

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "getloadavg", lambda: (11.7, 8.0, 4.0))
    assert load_bound(3.0) == pytest.approx(3.0 * 11.7 / 2)  # the 5.9 s of the SIGKILL test passes
    monkeypatch.setattr(os, "getloadavg", lambda: (0.5, 1.0, 1.0))
    assert load_bound(3.0) == 3.0
