"""``/comm/links`` (JSON, schema ``cosim.LinkArray``): one tick's links as columns, and back.

Light on purpose (numpy only): the reader and ``cosim validate`` import it without the link model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cosim.errors import FormatError

TOPIC = "/comm/links"
SCHEMA_NAME = "cosim.LinkArray"
LINK_TYPES: tuple[str, ...] = ("vehicle-vehicle", "vehicle-rsu", "vehicle-drone", "rsu-rsu", "rsu-drone", "drone-drone")
LOS_VALUES: tuple[str, ...] = ("los", "nlosv", "nlos")

#: Numeric columns: name -> (decimals written, description with unit).
NUMERIC_COLUMNS: dict[str, tuple[int, str]] = {
    "distance_m": (3, "3D distance between the two antennas [m]"),
    "path_loss_db": (3, "path loss of the channel model, without shadow fading [dB]"),
    "shadow_fading_db": (3, "shadow fading [dB] (> 0: extra loss); the same both ways"),
    "rx_power_dbm": (3, "received power [dBm]"),
    "snr_db": (3, "signal to noise ratio [dB]"),
    "per": (6, "packet error rate of one message at the configured MCS [0..1]"),
    "rate_bps": (0, "achievable rate: MCS rate x (1 - PER) [bit/s]"),
    "capacity_bps": (0, "attenuated Shannon bound alpha B log2(1 + SNR) [bit/s]"),
    "delay_ms": (4, "delay of the configured message: transmission + processing + access [ms]"),
    "delivery": (6, "probability that the message arrives within one tick: (1 - PER) if delay <= tick, else 0"),
}
TEXT_COLUMNS: dict[str, str] = {
    "tx": "transmitting agent id",
    "rx": "receiving agent id",
    "link_type": "|".join(LINK_TYPES),
    "los": "los | nlosv (an actor in between) | nlos (the static world in between)",
    "model": "channel model: tr37885_urban | tr37885_highway | tr38901_umi_sc | tr36777_<umi|uma|rma>_av | free_space",
}


def _column(desc: str, item_type: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": item_type}, "description": desc}


LINK_ARRAY_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": SCHEMA_NAME,
    "description": "Every ordered link between connected agents at one tick, as columns of equal length "
                   "(docs/episode_format.md section 3.11).",
    "type": "object",
    "required": ["timestamp_ns", "tick", "frame_id", "mcs", "message_bytes", "bandwidth_hz", "links"],
    "properties": {
        "timestamp_ns": {"type": "integer", "description": "simulation time since episode start [ns]"},
        "tick": {"type": "integer"},
        "frame_id": {"type": "string", "const": "map"},
        "mcs": {"type": "string", "description": "modulation and coding of the message"},
        "message_bytes": {"type": "integer", "description": "size of the message each agent sends [B]"},
        "bandwidth_hz": {"type": "number", "description": "channel bandwidth [Hz]"},
        "links": {
            "type": "object",
            "required": [*TEXT_COLUMNS, *NUMERIC_COLUMNS],
            "properties": {
                **{k: _column(v, "string") for k, v in TEXT_COLUMNS.items()},
                **{k: _column(v[1], "number") for k, v in NUMERIC_COLUMNS.items()},
            },
        },
    },
}


@dataclass(frozen=True)
class LinkSet:
    """One tick's L ordered links (tx -> rx) as arrays; see :data:`NUMERIC_COLUMNS` for units.

    ``tx``, ``rx``, ``link_type``, ``los``, ``model``: (L,) tuples of str; every numeric field (L,)
    float64.
    """

    tick: int
    t_ns: int
    tx: tuple[str, ...]
    rx: tuple[str, ...]
    link_type: tuple[str, ...]
    los: tuple[str, ...]
    model: tuple[str, ...]
    distance_m: np.ndarray
    path_loss_db: np.ndarray
    shadow_fading_db: np.ndarray
    rx_power_dbm: np.ndarray
    snr_db: np.ndarray
    per: np.ndarray
    rate_bps: np.ndarray
    capacity_bps: np.ndarray
    delay_ms: np.ndarray
    delivery: np.ndarray

    def __len__(self) -> int:
        return len(self.tx)

    def index(self, tx: str, rx: str) -> int:
        """Row of the link tx -> rx; ``KeyError`` when there is none."""
        for i, (a, b) in enumerate(zip(self.tx, self.rx, strict=True)):
            if a == tx and b == rx:
                return i
        raise KeyError(f"no link {tx} -> {rx} at tick {self.tick}")


def links_payload(links: LinkSet, mcs: str, message_bytes: int, bandwidth_hz: float) -> dict[str, Any]:
    """The ``/comm/links`` payload (schema :data:`LINK_ARRAY_SCHEMA`), numbers rounded as listed."""
    cols: dict[str, list[Any]] = {k: list(getattr(links, k)) for k in TEXT_COLUMNS}
    for name, (decimals, _) in NUMERIC_COLUMNS.items():
        values = np.round(np.asarray(getattr(links, name), np.float64), decimals)
        cols[name] = values.astype(np.int64).tolist() if decimals == 0 else values.tolist()
    return {
        "timestamp_ns": links.t_ns,
        "tick": links.tick,
        "frame_id": "map",
        "mcs": mcs,
        "message_bytes": int(message_bytes),
        "bandwidth_hz": float(bandwidth_hz),
        "links": cols,
    }


def decode_links(payload: dict[str, Any]) -> LinkSet:
    """A ``cosim.LinkArray`` payload as a :class:`LinkSet`; :class:`FormatError` naming what is wrong."""
    where = f"{SCHEMA_NAME} at t={payload.get('timestamp_ns') if isinstance(payload, dict) else '?'} ns"
    try:
        cols = payload["links"]
        n = len(cols["tx"])
        text = {k: tuple(str(v) for v in cols[k]) for k in TEXT_COLUMNS}
        nums = {k: np.asarray(cols[k], dtype=np.float64).reshape(-1) for k in NUMERIC_COLUMNS}
        tick, t_ns = int(payload["tick"]), int(payload["timestamp_ns"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(f"{where}: bad or missing field {exc}") from None
    lengths = {k: len(v) for k, v in {**text, **nums}.items()}
    if any(v != n for v in lengths.values()):
        raise FormatError(f"{where}: columns differ in length: {lengths}")
    bad_type = sorted(set(text["link_type"]) - set(LINK_TYPES))
    bad_los = sorted(set(text["los"]) - set(LOS_VALUES))
    if bad_type or bad_los:
        raise FormatError(f"{where}: unknown link_type {bad_type} / los {bad_los}; known: {LINK_TYPES} / {LOS_VALUES}")
    if not all(np.all(np.isfinite(v)) for v in nums.values()):
        raise FormatError(f"{where}: a numeric column holds NaN or infinity")
    if n and (nums["per"].min() < 0 or nums["per"].max() > 1 or nums["delivery"].min() < 0
              or nums["delivery"].max() > 1 or nums["distance_m"].min() < 0):
        raise FormatError(f"{where}: per / delivery outside [0, 1] or a negative distance")
    return LinkSet(tick, t_ns, **text, **nums)

