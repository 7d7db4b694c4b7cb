"""The registry of a plug-in seam: name -> entry (link models, evaluation metrics, sensor kinds).

The semantics of every registry in cosim (drone backends, map generators, scan patterns, export formats,
batch executors): registering a name twice is an error (a programming mistake, ``ValueError``), asking
for an unknown name is an :class:`~cosim.errors.InputError` that lists the known names (it usually comes
from a scenario or a command line).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from cosim.errors import InputError

T = TypeVar("T")


class Registry(Generic[T]):
    """Entries by name; ``what`` names the kind of entry in messages ("link model", "metric")."""

    def __init__(self, what: str):
        self.what = what
        self._entries: dict[str, T] = {}

    def add(self, name: str, entry: T) -> T:
        if name in self._entries:
            raise ValueError(f"{self.what} {name!r} is already registered")
        self._entries[name] = entry
        return entry

    def register(self, name: str) -> Callable[[T], T]:
        """Decorator form of :meth:`add`."""
        return lambda entry: self.add(name, entry)

    def remove(self, name: str) -> None:
        """Drop an entry (tests that register a toy one clean up with this)."""
        del self._entries[name]

    def get(self, name: str) -> T:
        try:
            return self._entries[name]
        except KeyError:
            raise InputError(f"unknown {self.what} {name!r}; known: {', '.join(self.names())}") from None

    def names(self) -> list[str]:
        """The registered names, sorted."""
        return sorted(self._entries)

    def items(self) -> Iterator[tuple[str, T]]:
        """(name, entry) in registration order (the order tables and messages use)."""
        return iter(list(self._entries.items()))

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __len__(self) -> int:
        return len(self._entries)
