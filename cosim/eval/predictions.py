"""Prediction files: the format users write for ``cosim eval`` (docs/evaluation.md), its validator, a writer.

PREDICTIONS is a ``.jsonl`` file or a folder of them (read in name order). One line (record) per
(episode, tick, ego agent, collaboration setting)::

    {"episode": "all-urban-0000", "tick": 3, "ego": "vehicle_0", "agents": "all",
     "boxes": [{"center_m": [12.1, -3.4, 0.8], "size_m": [4.5, 1.9, 1.6], "yaw_rad": 0.02,
                "class": "car", "score": 0.93}],
     "bev": "bev/all-urban-0000_3_vehicle_0_all.npz"}

Boxes are in the ego's LiDAR frame (``<ego>/lidar``, FLU); ``agents`` (default ``all``) names which
agent types the model used (:data:`SETTINGS`); ``bev`` (optional) is an ``.npz`` file, relative to
the ``.jsonl`` file, with one (rows, columns) array per BEV layer name, in the grid of the episode's
``/<ego>/bev``; ``bytes_sent`` (optional, an integer) the bytes the collaborators sent the ego for the frame
(``cosim learn predict`` writes it; ``cosim eval`` reports its mean beside AP). A malformed file raises one
:class:`PredictionError` naming file, line and field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cosim.errors import InputError

#: Collaboration settings: which agents' data a model used, as agent kinds (``ego``: the ego alone).
SETTINGS: dict[str, tuple[str, ...]] = {
    "ego": (),
    "vehicles": ("vehicle",),
    "vehicles+rsus": ("vehicle", "rsu"),
    "vehicles+drones": ("vehicle", "drone"),
    "all": ("vehicle", "rsu", "drone"),
}
RECORD_KEYS = {"episode", "tick", "ego", "agents", "boxes", "bev", "bytes_sent"}
BOX_KEYS = {"center_m", "size_m", "yaw_rad", "class", "score"}


class PredictionError(InputError):
    """A prediction file is malformed: ``source`` (file), ``line`` (1-based record line), ``field``."""

    def __init__(self, source: Path | str, line: int | None, field: str, message: str):
        self.source, self.line, self.field = str(source), line, field
        where = f"{source}:{line}" if line is not None else str(source)
        super().__init__(f"{where}: {field}: {message}" if field else f"{where}: {message}")


@dataclass(frozen=True)
class FramePrediction:
    """One record: boxes (N) in the ego LiDAR frame; ``bev_path`` absolute or None."""

    episode: str
    tick: int
    ego: str
    agents: str
    centers_m: np.ndarray  # (N, 3) [m]
    sizes_m: np.ndarray  # (N, 3) [m] length, width, height
    yaws_rad: np.ndarray  # (N,) [rad]
    classes: tuple[str, ...]
    scores: np.ndarray  # (N,)
    bev_path: Path | None
    source: str
    line: int
    bytes_sent: int | None = None  # what the collaborators sent the ego for this frame [bytes], when told

    @property
    def key(self) -> tuple[str, int, str, str]:
        return (self.episode, self.tick, self.ego, self.agents)


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _vector(rec: dict, key: str, n: int, where: str, positive: bool = False) -> list[float]:
    v = rec.get(key)
    if not isinstance(v, list) or len(v) != n or not all(_number(x) for x in v):
        raise ValueError(f"{where}{key}", f"must be a list of {n} finite numbers, got {json.dumps(v)[:60]}")
    if positive and not all(x > 0 for x in v):
        raise ValueError(f"{where}{key}", f"must be > 0, got {v}")
    return [float(x) for x in v]


def parse_record(obj: Any, source: Path, line: int) -> FramePrediction:
    """Check one decoded JSON line and turn it into a :class:`FramePrediction`."""
    try:
        if not isinstance(obj, dict):
            raise ValueError("", f"a record must be a JSON object, got {type(obj).__name__}")
        unknown = sorted(set(obj) - RECORD_KEYS)
        if unknown:
            raise ValueError(unknown[0], f"unknown key; a record has {', '.join(sorted(RECORD_KEYS))}")
        for key in ("episode", "tick", "ego", "boxes"):
            if key not in obj:
                raise ValueError(key, "missing")
        if not isinstance(obj["episode"], str) or not obj["episode"]:
            raise ValueError("episode", f"must be a non-empty string (an episode id), got {obj['episode']!r}")
        tick = obj["tick"]
        if not isinstance(tick, int) or isinstance(tick, bool) or tick < 0:
            raise ValueError("tick", f"must be an integer >= 0, got {tick!r}")
        if not isinstance(obj["ego"], str) or not obj["ego"]:
            raise ValueError("ego", f"must be an agent id such as 'vehicle_0', got {obj['ego']!r}")
        agents = obj.get("agents", "all")
        if agents not in SETTINGS:
            raise ValueError("agents", f"must be one of {', '.join(SETTINGS)}, got {agents!r}")
        boxes = obj["boxes"]
        if not isinstance(boxes, list):
            raise ValueError("boxes", f"must be a list of boxes, got {type(boxes).__name__}")
        centers, sizes, yaws, classes, scores = [], [], [], [], []
        for i, b in enumerate(boxes):
            where = f"boxes[{i}]."
            if not isinstance(b, dict):
                raise ValueError(f"boxes[{i}]", "must be an object with " + ", ".join(sorted(BOX_KEYS)))
            extra = sorted(set(b) - BOX_KEYS)
            if extra:
                raise ValueError(where + extra[0], f"unknown key; a box has {', '.join(sorted(BOX_KEYS))}")
            for key in sorted(BOX_KEYS):
                if key not in b:
                    raise ValueError(where + key, "missing")
            centers.append(_vector(b, "center_m", 3, where))
            sizes.append(_vector(b, "size_m", 3, where, positive=True))
            if not _number(b["yaw_rad"]):
                raise ValueError(where + "yaw_rad", f"must be a finite number [rad], got {b['yaw_rad']!r}")
            yaws.append(float(b["yaw_rad"]))
            if not isinstance(b["class"], str) or not b["class"]:
                raise ValueError(where + "class", f"must be a class name such as 'car', got {b['class']!r}")
            classes.append(b["class"])
            if not _number(b["score"]):
                raise ValueError(where + "score", f"must be a finite number, got {b['score']!r}")
            scores.append(float(b["score"]))
        sent = obj.get("bytes_sent")
        if sent is not None and (not isinstance(sent, int) or isinstance(sent, bool) or sent < 0):
            raise ValueError("bytes_sent", f"must be an integer >= 0 (bytes), got {sent!r}")
        bev = obj.get("bev")
        if bev is not None and (not isinstance(bev, str) or not bev.endswith(".npz")):
            raise ValueError("bev", f"must be the path of an .npz file relative to {source.name}, got {bev!r}")
    except ValueError as exc:
        field, message = exc.args
        raise PredictionError(source, line, field, message) from None
    return FramePrediction(
        obj["episode"], tick, obj["ego"], agents,
        np.array(centers, np.float64).reshape(-1, 3), np.array(sizes, np.float64).reshape(-1, 3),
        np.array(yaws, np.float64), tuple(classes), np.array(scores, np.float64),
        (source.parent / bev) if bev else None, str(source), line, sent,
    )


def prediction_files(path: Path) -> list[Path]:
    path = Path(path)
    if path.is_file():
        return [path]
    if path.is_dir():
        files = sorted(path.glob("*.jsonl"))
        if not files:
            raise InputError(f"{path}: no *.jsonl prediction files in this folder (see docs/evaluation.md)")
        return files
    raise InputError(f"no predictions at {path}: give a .jsonl file or a folder of them")


def read_predictions(path: Path) -> list[FramePrediction]:
    """Every record of a prediction file or folder; :class:`PredictionError` on the first malformed one."""
    out: list[FramePrediction] = []
    seen: dict[tuple[str, int, str, str], str] = {}
    for f in prediction_files(path):
        with open(f, encoding="utf-8") as stream:
            for n, text in enumerate(stream, 1):
                if not text.strip():
                    continue
                try:
                    obj = json.loads(text)
                except json.JSONDecodeError as exc:
                    raise PredictionError(f, n, "", f"not valid JSON ({exc.msg} at column {exc.colno})") from None
                rec = parse_record(obj, f, n)
                where = f"{f}:{n}"
                if rec.key in seen:
                    raise PredictionError(f, n, "", f"second record for episode {rec.episode!r} tick {rec.tick} "
                                                    f"ego {rec.ego!r} agents {rec.agents!r} (first at {seen[rec.key]})")
                seen[rec.key] = where
                out.append(rec)
    return out


def record_json(episode: str, tick: int, ego: str, agents: str, centers_m: np.ndarray, sizes_m: np.ndarray,
                yaws_rad: np.ndarray, classes: Iterable[str], scores: np.ndarray, bev: str | None = None,
                bytes_sent: int | None = None) -> str:
    """One JSON line of the format (numbers rounded to 1 mm / 1e-5 rad, so files are compact and stable)."""
    boxes = [
        {"center_m": [round(float(v), 3) for v in c], "size_m": [round(float(v), 3) for v in s],
         "yaw_rad": round(float(y), 5), "class": k, "score": round(float(p), 5)}
        for c, s, y, k, p in zip(centers_m, sizes_m, yaws_rad, classes, scores, strict=True)
    ]
    rec: dict[str, Any] = {"episode": episode, "tick": int(tick), "ego": ego, "agents": agents, "boxes": boxes}
    if bev:
        rec["bev"] = bev
    if bytes_sent is not None:
        rec["bytes_sent"] = int(bytes_sent)
    return json.dumps(rec, separators=(",", ":"))


def write_prediction_lines(out: Path, lines: Iterable[str]) -> Path:
    """Write a prediction file (one :func:`record_json` line each) whole or not at all: into
    ``.<name>.partial`` beside it, renamed when complete, so a killed run never leaves a file that looks
    finished (and a reader never sees half of one)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.partial")
    tmp.write_text("".join(line + "\n" for line in lines), encoding="utf-8")
    tmp.replace(out)
    return out


def iter_bev_layers(rec: FramePrediction, shape: tuple[int, int], layers: Iterable[str]
                    ) -> Iterator[tuple[str, np.ndarray]]:
    """The predicted BEV layers of a record, checked against the grid ``shape`` and layer names."""
    if rec.bev_path is None:
        return
    layers = tuple(layers)
    known = set(layers)
    try:
        data = np.load(rec.bev_path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise PredictionError(rec.source, rec.line, "bev", f"cannot read {rec.bev_path}: {exc}") from None
    with data:
        for name in data.files:
            if name not in known:
                raise PredictionError(rec.source, rec.line, "bev",
                                      f"{rec.bev_path.name} has layer {name!r}; the episode's BEV layers are "
                                      f"{', '.join(layers)}")
            arr = data[name]
            if arr.shape != shape:
                raise PredictionError(rec.source, rec.line, "bev",
                                      f"layer {name!r} of {rec.bev_path.name} has shape {arr.shape}; the "
                                      f"episode's grid is {shape} (rows, columns)")
            yield name, arr.astype(bool)
