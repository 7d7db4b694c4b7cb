"""Breakdown tables written as Markdown, CSV and JSON, and their bar plots (matplotlib, Agg backend)."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


def fmt(v: Any, digits: int = 1) -> str:
    """A cell: floats as percentages-style numbers with ``digits`` decimals, NaN/None as ``n/a``."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


@dataclass
class Table:
    """A titled table: ``columns`` names, ``rows`` lists of cells (str, int, float or None)."""

    name: str
    title: str
    columns: list[str]
    rows: list[list[Any]] = field(default_factory=list)
    note: str = ""

    def markdown(self, digits: int = 1) -> str:
        lines = [f"### {self.title}", ""]
        if self.note:
            lines += [self.note, ""]
        lines.append("| " + " | ".join(self.columns) + " |")
        lines.append("|" + "|".join("---" if i == 0 else "---:" for i in range(len(self.columns))) + "|")
        lines += ["| " + " | ".join(fmt(c, digits) for c in row) + " |" for row in self.rows]
        return "\n".join(lines) + "\n"

    def csv_rows(self) -> list[list[Any]]:
        return [[self.name, *[("" if c is None or (isinstance(c, float) and math.isnan(c)) else
                               (round(c, 6) if isinstance(c, float) else c)) for c in row]] for row in self.rows]

    def as_dict(self) -> dict[str, Any]:
        def clean(c: Any) -> Any:
            return None if isinstance(c, float) and math.isnan(c) else c

        return {"name": self.name, "title": self.title, "columns": self.columns,
                "rows": [[clean(c) for c in row] for row in self.rows], "note": self.note}


def write_tables(tables: Sequence[Table], out_dir: Path, stem: str, header: str = "", extra: dict | None = None
                 ) -> list[Path]:
    """``<stem>.md`` (all tables), ``<stem>.csv`` (long: table name first), ``<stem>.json``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    md = out_dir / f"{stem}.md"
    md.write_text((header + "\n" if header else "") + "\n".join(t.markdown() for t in tables), encoding="utf-8")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for t in tables:
        w.writerow(["table", *t.columns])
        w.writerows(t.csv_rows())
    (out_dir / f"{stem}.csv").write_text(buf.getvalue(), encoding="utf-8")
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps({"tables": [t.as_dict() for t in tables], **(extra or {})}, indent=1) + "\n",
                  encoding="utf-8")
    return [md, out_dir / f"{stem}.csv", js]


def bar_plot(path: Path, title: str, groups: Sequence[str], series: dict[str, Sequence[float]],
             panels: dict[str, dict[str, Sequence[float]]] | None = None, ylabel: str = "%",
             ylim: tuple[float, float] = (0.0, 100.0)) -> Path:
    """Grouped bars: one group per condition value, one bar per series; several panels side by side.

    ``panels`` maps a panel title to its ``series``; without it one panel ``series`` is drawn.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = panels or {title: series}
    fig, axes = plt.subplots(1, len(panels), figsize=(max(4.5, 1.2 * len(groups) + 2.5) * len(panels), 3.6),
                             squeeze=False)
    for ax, (ptitle, pseries) in zip(axes[0], panels.items(), strict=True):
        n = max(len(pseries), 1)
        width = 0.8 / n
        for k, (label, values) in enumerate(pseries.items()):
            xs = [g + (k - (n - 1) / 2) * width for g in range(len(groups))]
            vals = [0.0 if v is None or math.isnan(v) else v for v in values]
            bars = ax.bar(xs, vals, width, label=label)
            for b, v in zip(bars, values, strict=True):
                if v is None or math.isnan(v):
                    ax.annotate("n/a", (b.get_x() + b.get_width() / 2, 0), ha="center", va="bottom", fontsize=6)
        ax.set_xticks(range(len(groups)), list(groups))
        ax.set_ylim(*ylim)
        ax.set_ylabel(ylabel)
        ax.set_title(ptitle, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(title if len(panels) > 1 else "", fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
