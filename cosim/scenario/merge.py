"""Merging scenario data field by field: what ``extends:``, the partial rigs and the LiDAR presets share (plain
JSON-like data; no schema)."""

from __future__ import annotations

from typing import Any


def merge_fields(base: Any, over: Any) -> Any:
    """Deep-merge mappings field by field; anything else in ``over`` (a value, a list) replaces ``base``."""
    if isinstance(base, dict) and isinstance(over, dict):
        return {**base, **{k: merge_fields(base[k], v) if k in base else v for k, v in over.items()}}
    return over
