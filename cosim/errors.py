"""One exception tree for everything cosim raises on purpose.

The CLI maps :class:`InputError` (and children) to exit status 2 and every other
:class:`CosimError` to exit status 1.
"""

from __future__ import annotations

from collections.abc import Sequence


class CosimError(Exception):
    """Base of every error cosim raises deliberately."""


class InputError(CosimError):
    """The user gave something unusable (file, flag, value). Exit status 2."""


class ScenarioError(InputError):
    """A scenario file or override is invalid.

    ``path`` is the dotted key path (``agents.drones.0.strategy``), ``line`` the 1-based YAML
    line when known, ``source`` the file it came from.
    """

    def __init__(self, message: str, *, path: str = "", line: int | None = None, source: str = "",
                 problems: Sequence[ScenarioError] = (), more: int = 0):
        self.path = path
        self.line = line
        self.source = source
        self.detail = message
        #: Several problems found at once (``message`` then says how many): one ScenarioError each, in file
        #: order; ``more`` counts those left out. ``path``, ``line`` and ``source`` are the first one's.
        self.problems = list(problems)
        self.more = more
        if self.problems:
            listed = "".join(f"\n  {p}" for p in self.problems)
            tail = f"\n  ... and {more} more" if more else ""
            super().__init__(f"{self.problems[0].source or 'scenario'}: {message}:{listed}{tail}")
            return
        where = source or "scenario"
        if line is not None:
            where += f":{line}"
        key = f" {path}:" if path else ""
        super().__init__(f"{where}:{key} {message}")


class WorkerError(CosimError):
    """A simulation worker failed, died, or replied with an error."""

    def __init__(self, worker: str, message: str, *, tick: int | None = None):
        self.worker = worker
        self.tick = tick
        at = f" at tick {tick}" if tick is not None else ""
        super().__init__(f"{worker} worker{at}: {message}")


class SyncTimeout(WorkerError):
    """A worker did not answer a lockstep query in time."""


class CollisionError(CosimError):
    """A drone hit the static world or the ground."""

    def __init__(self, agent_id: str, tick: int, what: str):
        self.agent_id = agent_id
        self.tick = tick
        super().__init__(f"{agent_id} collided with {what} at tick {tick}")


class DroneCollisionError(CollisionError):
    """Two drones came so close that their rotors touch."""

    def __init__(self, agent_id: str, other_id: str, tick: int, distance_m: float):
        self.other_id = other_id
        self.distance_m = distance_m
        super().__init__(agent_id, tick, f"{other_id} ({distance_m:.2f} m between their centres)")


class FormatError(CosimError):
    """An episode file does not follow docs/episode_format.md."""


class EpisodeFileError(FormatError, InputError):
    """The file given as an episode cannot be opened as one (truncated, not MCAP, no cosim metadata, a format
    version this reader does not know): bad input, exit status 2, the same message for every command."""


class ClientError(WorkerError):
    """A closed-loop client (``cosim.client``) went away or broke the protocol during an episode."""

    def __init__(self, client: str, message: str, *, tick: int | None = None):
        self.worker = f"client {client}"
        self.client = client
        self.tick = tick
        at = f" at tick {tick}" if tick is not None else ""
        CosimError.__init__(self, f"client {client!r}{at}: {message}")


class ClientTimeout(ClientError, SyncTimeout):
    """A closed-loop client did not send its action for a tick in time."""


class ActionRejected(CosimError):
    """An action sent by a client was refused on arrival (unknown agent, impossible value); the episode goes on."""
