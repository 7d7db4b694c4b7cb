"""argparse ``type=`` checks for every cosim subcommand: each refuses a bad value with one clear message.

A check takes the text as typed and returns the value (``int`` or ``float`` for numbers, the text unchanged for
paths) or raises :class:`argparse.ArgumentTypeError`. Number messages read after the option's name
(``--lr must be a finite number, got nan``); path messages name the path (``--out: /tmp/x is a file, not a
folder``). ``cosim.cli`` prints either as one line, ``cosim: error: ...``, exit status 2.

Every check is a :class:`Check`, whose fields say what it refuses (``tests/test_cli_args.py`` walks every
subcommand's options and drives each with the values its check must refuse). A path check looks at the file
system without changing it: an output folder is made by the command, after every check has passed.
:func:`check_output_folder` is the same test for library code (raises :class:`~cosim.errors.InputError`).
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cosim.errors import InputError

#: The kinds of :class:`Check`: numbers, then paths.
NUMBER_KINDS = ("float", "int")
PATH_KINDS = ("output_folder", "output_file", "input_file", "input_folder", "input_path")


def shown(text: str, limit: int = 120) -> str:
    """``text`` for a message: control characters escaped, a long text shortened."""
    out = text if text.isprintable() else text.encode("unicode_escape", "backslashreplace").decode("ascii")
    return out if len(out) <= limit else f"{out[: limit - 20]}... ({len(text)} characters)"


@dataclass(frozen=True)
class Check:
    """One argparse ``type=``: ``check(text)`` gives the value or raises ``ArgumentTypeError``.

    Numbers (``kind`` "float" or "int"): finite, at least ``low`` (more than ``low`` when ``low_open``), at most
    ``high``; ``unit`` is said in the message, ``noun`` (when given) starts it. Paths (``kind`` in
    :data:`PATH_KINDS`): ``noun`` names what the path holds in the message. ``items``: a comma-separated list of
    such values (a list comes back).
    """

    kind: str
    low: float | None = None
    low_open: bool = False
    high: float | None = None
    unit: str = ""
    noun: str = ""
    items: bool = False

    @property
    def __name__(self) -> str:  # argparse names a type by it in its own messages
        return self.kind

    def __call__(self, text: str) -> Any:
        if self.items:
            parts = [p.strip() for p in text.split(",")]
            if not all(parts):
                raise argparse.ArgumentTypeError(f"must be a comma-separated list without empty entries, got "
                                                 f"{shown(text)!r}")
            one = _ONE[self.kind]
            return [one(self, p) for p in parts]
        return _ONE[self.kind](self, text)

    def bounds(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.low is not None and self.high is not None:
            return f"{self.low:g} to {self.high:g}{unit}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {self.low:g}{unit}"
        if self.high is not None:
            return f"<= {self.high:g}{unit}"
        return ""

    def refuses(self, value: float) -> bool:
        """Whether a finite number is out of this check's bounds."""
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return True
        return self.high is not None and value > self.high


def _number(check: Check, text: str) -> float | int:
    bounds = check.bounds()
    noun = f"{check.noun} " if check.noun else ""
    wanted = f"{noun}must be {'a whole number' if check.kind == 'int' else 'a finite number'}" + (
        f" {bounds}" if bounds else "")
    try:
        value: float | int = int(text.strip(), 10) if check.kind == "int" else float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{wanted}, got {shown(text)!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{wanted}, got {shown(text.strip())}")
    if check.refuses(value):
        raise argparse.ArgumentTypeError(f"{noun}must be {bounds}, got {shown(text.strip())}")
    return value


def _a(noun: str) -> str:
    return f"{'an' if noun[:1] in 'aeiou' else 'a'} {noun}"


def _path_text(text: str) -> Path:
    if not text:
        raise argparse.ArgumentTypeError("an empty path")
    if "\0" in text:
        raise argparse.ArgumentTypeError(f"{shown(text)}: a path cannot hold a NUL character")
    return Path(text)


def _nearest_existing(path: Path) -> Path:
    probe = path
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    return probe


def _output(check: Check, text: str) -> str:
    path = _path_text(text)
    folder = check.kind == "output_folder"
    if path.exists():
        if folder and not path.is_dir():
            raise argparse.ArgumentTypeError(f"{shown(text)} is a file, not a folder")
        if not folder and path.is_dir():
            raise argparse.ArgumentTypeError(f"{shown(text)} is a folder, not {_a(check.noun or 'file')}")
        return text
    probe = _nearest_existing(path.absolute().parent)
    if not probe.is_dir():
        raise argparse.ArgumentTypeError(f"cannot make {shown(text)}: {shown(str(probe))} is a file, not a folder")
    return text


def _input(check: Check, text: str) -> str:
    path = _path_text(text)
    noun = check.noun or {"input_file": "file", "input_folder": "folder"}.get(check.kind, "file or folder")
    if not path.exists():
        raise argparse.ArgumentTypeError(f"no {noun} at {shown(text)}")
    if check.kind == "input_file" and path.is_dir():
        raise argparse.ArgumentTypeError(f"{shown(text)} is a folder, not {_a(noun)}")
    if check.kind == "input_folder" and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{shown(text)} is a file, not {_a(noun)}")
    if not os.access(path, os.R_OK | (os.X_OK if path.is_dir() else 0)):
        raise argparse.ArgumentTypeError(f"cannot read {shown(text)}: permission denied")
    return text


_ONE: dict[str, Callable[[Check, str], Any]] = {
    "float": _number, "int": _number, "output_folder": _output, "output_file": _output,
    "input_file": _input, "input_folder": _input, "input_path": _input,
}

#: Any finite number.
finite_float = Check("float")
#: A finite number > 0.
positive_float = Check("float", low=0.0, low_open=True)
#: A finite number >= 0.
non_negative_float = Check("float", low=0.0)
#: A fraction from 0 to 1 (probabilities, rates).
fraction = Check("float", low=0.0, high=1.0)
#: Any whole number.
whole_number = Check("int")
#: A whole number >= 1 (counts, steps, sizes).
positive_int = Check("int", low=1)
#: A whole number >= 0 (0 usually: none, off).
non_negative_int = Check("int", low=0)
#: A folder the command writes into: missing (it is made) or a folder, not a file, with no file above it.
output_folder = Check("output_folder")
#: A file the command writes: not a folder, with no file above it.
output_file = Check("output_file")
#: An existing, readable file.
input_file = Check("input_file")
#: An existing, readable folder.
input_folder = Check("input_folder")
#: An existing, readable file or folder (a dataset: one episode or a batch folder).
input_path = Check("input_path")


def float_in(low: float, high: float, unit: str = "") -> Check:
    """A finite number from ``low`` to ``high`` (``unit`` in the message)."""
    return Check("float", low=low, high=high, unit=unit)


def int_in(low: int, high: int, unit: str = "") -> Check:
    """A whole number from ``low`` to ``high`` (``unit`` in the message)."""
    return Check("int", low=low, high=high, unit=unit)


def at_least(low: float, unit: str = "", *, whole: bool = False, noun: str = "", above: bool = False) -> Check:
    """A finite number (a whole one with ``whole``) >= ``low`` (> ``low`` with ``above``); ``noun`` starts the
    message (``scale must be a finite number > 0``)."""
    return Check("int" if whole else "float", low=low, low_open=above, unit=unit, noun=noun)


def path(kind: str, noun: str) -> Check:
    """A path check of ``kind`` (:data:`PATH_KINDS`) whose messages call the path ``noun`` (``"episode file"``)."""
    if kind not in PATH_KINDS:
        raise ValueError(f"unknown path kind {kind!r}; known: {', '.join(PATH_KINDS)}")
    return Check(kind, noun=noun)


def comma_list(item: Check) -> Check:
    """A comma-separated list of ``item`` values (``a,b,c``): a list comes back."""
    return Check(item.kind, item.low, item.low_open, item.high, item.unit, item.noun, items=True)


def check_output_folder(folder: Path | str, option: str = "--out") -> None:
    """:data:`output_folder`'s test for library code: raises :class:`InputError` ``"<option>: <problem>"``."""
    try:
        output_folder(str(folder))
    except argparse.ArgumentTypeError as exc:
        raise InputError(f"{option}: {exc}") from None
