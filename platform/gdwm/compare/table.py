"""The comparison table: factor columns, grouped metric columns, best / second-best marks per column.

Marks are direction-aware and compare values at the shown precision, so values that print the same tie and share
a mark (as in the paper's tables). Missing values and failed rows never get or take a mark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import groupby

from gdwm.compare.layout import Column, Direction, LayoutConfig, resolve_columns
from gdwm.compare.runs import Row

BEST, SECOND = "best", "second"
MISSING = "–"


def mark_column(values: list[float | None], direction: Direction, precision: int) -> list[str | None]:
    """``best`` / ``second`` / None per value; None values are excluded; ties share a mark."""
    shown = [None if v is None or math.isnan(v) else round(v, precision) for v in values]
    ranked = sorted({v for v in shown if v is not None}, reverse=direction is Direction.higher)
    place = {v: mark for v, mark in zip(ranked, (BEST, SECOND), strict=False)}
    return [place.get(v) if v is not None else None for v in shown]


def normalise(values: list[float | None], direction: Direction) -> list[float | None]:
    """Fig. 1 (radar) radii: Metric_i / Metric_max (higher-better), Metric_min / Metric_i (lower-better), in [0, 1].

    A zero best value (all zero, or a perfect zero error) gives radius 1 to the rows that reach it."""
    present = [v for v in values if v is not None and not math.isnan(v)]
    if not present:
        return [None] * len(values)
    best = max(present) if direction is Direction.higher else min(present)
    out: list[float | None] = []
    for v in values:
        if v is None or math.isnan(v):
            out.append(None)
        elif v == best:
            out.append(1.0)
        else:
            ratio = v / best if direction is Direction.higher else (best / v if v else 0.0)
            out.append(min(max(ratio, 0.0), 1.0))
    return out


@dataclass
class Table:
    title: str
    factors: list[str]
    columns: list[Column]
    rows: list[Row]
    precision: int = 2
    marks: dict[tuple[int, str], str] = field(default_factory=dict)
    """(row index, metric) -> ``best`` | ``second``."""

    def value(self, i: int, metric: str) -> float | None:
        v = self.rows[i].metrics.get(metric)
        return None if v is None or math.isnan(v) else v

    def fmt(self, v: float | None) -> str:
        return MISSING if v is None else f"{v:.{self.precision}f}"

    def factor(self, i: int, name: str) -> str:
        return self.rows[i].factors.get(name, MISSING)

    @property
    def has_notes(self) -> bool:
        return any(r.failed for r in self.rows)

    def groups(self) -> list[tuple[str, int]]:
        """Consecutive metric columns sharing a group: (group, span)."""
        return [(g, len(list(cols))) for g, cols in groupby(self.columns, key=lambda c: c.group)]

    def index_of(self, key: str) -> int:
        """Row whose label or run id (or a run id prefix of 8+ characters) is ``key``."""
        for i, r in enumerate(self.rows):
            if key in (r.label, r.run_id) or (len(key) >= 8 and r.run_id.startswith(key)):
                return i
        raise KeyError(key)

    def deltas(self, base: int) -> list[list[float | None]]:
        """Per row and column: value - baseline value (None where either is missing)."""
        out = []
        for i in range(len(self.rows)):
            row = []
            for c in self.columns:
                v, b = self.value(i, c.metric), self.value(base, c.metric)
                row.append(None if v is None or b is None else v - b)
            out.append(row)
        return out


def build_table(rows: list[Row], layout: LayoutConfig) -> Table:
    """Columns from the layout (plus discovered ones); factors in order of first appearance; marks per column."""
    columns = resolve_columns(layout, {m for r in rows for m in r.metrics})
    factors = list(dict.fromkeys(f for r in rows for f in r.factors))
    table = Table(layout.title or layout.name, factors, columns, rows, layout.precision)
    for c in columns:
        values = [None if r.failed else table.value(i, c.metric) for i, r in enumerate(rows)]
        for i, mark in enumerate(mark_column(values, c.direction, layout.precision)):
            if mark:
                table.marks[i, c.metric] = mark
    return table
