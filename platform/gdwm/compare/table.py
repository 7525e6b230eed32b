"""The comparison table: factor columns, grouped metric columns, cells with their uncertainty, earned marks.

A cell is the mean over a row's finished seeds with its std (or, for one seed, a bootstrap interval over the
held-out samples); bold / underline are given by significance tests (``stats``), and ``legend`` says which.
Missing values and failed rows never get or take a mark. Values print rounded half up, as the paper's tables do.
``notes`` (every format prints them under the legend) say which metrics are official or approximate and which
stand on proxy data (from the trials' evaluation stage runs; a proxy table's title says so), and which encoders
each row used (the layout's ``encoders`` params).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import groupby

from gdwm.compare.layout import Column, Direction, LayoutConfig, resolve_columns
from gdwm.compare.rounding import fmt
from gdwm.compare.runs import Row
from gdwm.compare.stats import BEST, SECOND, Cell, RowInput, Seed, Settings, analyse

__all__ = ["BEST", "MISSING", "SECOND", "Table", "build_table", "normalise"]

MISSING = "–"


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
    cells: dict[tuple[int, str], Cell] = field(default_factory=dict)
    """(row index, metric) -> mean, std, n and interval; absent = not logged."""
    marks: dict[tuple[int, str], str] = field(default_factory=dict)
    """(row index, metric) -> ``best`` | ``second``."""
    legend: str = ""
    """What the cells and marks mean and which test gave the marks; every format prints it."""
    notes: list[str] = field(default_factory=list)
    """Official / approximate metrics, proxy data, encoders per row (``table_notes``); every format prints them."""

    def cell(self, i: int, metric: str) -> Cell | None:
        return self.cells.get((i, metric))

    def value(self, i: int, metric: str) -> float | None:
        """The mean over the row's seeds (what deltas, bars and the radar use)."""
        c = self.cells.get((i, metric))
        return None if c is None else c.mean

    def fmt(self, v: float | None) -> str:
        return MISSING if v is None else fmt(v, self.precision)

    def parts(self, i: int, metric: str) -> tuple[str, str, str]:
        """(value, uncertainty, count): ``35.10``, ``± 1.20`` or ``[33.02, 37.21]`` or empty, ``(n=2)`` or empty.

        The count shows when fewer seeds than planned finished; a failed row shows its values alone."""
        c = self.cells.get((i, metric))
        if c is None:
            return MISSING, "", ""
        if self.rows[i].failed:
            return self.fmt(c.mean), "", ""
        if c.std is not None:
            unc = f"± {self.fmt(c.std)}"
        elif c.ci_low is not None and c.ci_high is not None:
            unc = f"[{self.fmt(c.ci_low)}, {self.fmt(c.ci_high)}]"
        else:
            unc = ""
        return self.fmt(c.mean), unc, f"(n={c.n})" if c.n < self.rows[i].planned else ""

    def text(self, i: int, metric: str) -> str:
        """The cell as one line: ``35.10 ± 1.20 (n=2)``."""
        return " ".join(filter(None, self.parts(i, metric)))

    def factor(self, i: int, name: str) -> str:
        return self.rows[i].factors.get(name, MISSING)

    @property
    def caption(self) -> list[str]:
        """The legend, then the notes: the lines every format prints under the table."""
        return [x for x in (self.legend, *self.notes) if x]

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
        """Per row and column: mean - baseline mean (None where either is missing)."""
        out = []
        for i in range(len(self.rows)):
            row = []
            for c in self.columns:
                v, b = self.value(i, c.metric), self.value(base, c.metric)
                row.append(None if v is None or b is None else v - b)
            out.append(row)
        return out


def row_input(row: Row) -> RowInput:
    """What the statistics need of a row: its counted trials' metrics and sample sets, planned seeds, failure."""
    seeds = [Seed(t.metrics, t.samples, t.seed) for t in row.counted]
    return RowInput(row.label, seeds, row.planned, row.failed)


def _name(c: Column) -> str:
    return " ".join(filter(None, (c.group, c.header)))


def table_notes(rows: list[Row], columns: list[Column], encoders: list[str]) -> tuple[list[str], bool]:
    """(notes, proxy): which columns the trials' evaluations labelled official / approximate (a metric labelled
    both ways by different trials is "mixed"), what stands in for a proxy column's data, and per row the values of
    the ``encoders`` params. ``proxy``: some column was computed on proxy data."""
    trials = [t for r in rows for t in r.counted]
    labels: dict[str, list[str]] = {}
    proxies: dict[str, list[str]] = {}
    for c in columns:
        found = {t.labels[c.metric] for t in trials if c.metric in t.metrics and c.metric in t.labels}
        if found:
            labels.setdefault(found.pop() if len(found) == 1 else "mixed", []).append(_name(c))
        for what in dict.fromkeys(t.proxy[c.metric] for t in trials if c.metric in t.metrics and c.metric in t.proxy):
            proxies.setdefault(what, []).append(_name(c))
    notes = []
    if labels:
        words = {"official": "Official (computed as the benchmark does)", "approximate": "Approximate",
                 "mixed": "Official in some trials, approximate in others"}  # fmt: skip
        parts = [f"{words.get(k, k.capitalize())}: {', '.join(v)}" for k, v in sorted(labels.items(), key=_order)]
        notes.append("Metrics. " + ". ".join(parts) + ".")
    if proxies:
        notes.append("Proxy: " + "; ".join(f"{', '.join(cols)}: {what}" for what, cols in proxies.items()) + ".")
    if encoders:
        per_row = {r.label: [r.param(k) for k in encoders] for r in rows}
        per_row = {label: v for label, v in per_row.items() if any(x is not None for x in v)}
        if per_row:
            head = f"Encoders ({', '.join(encoders)})"
            values = {label: ", ".join(MISSING if x is None else x for x in v) for label, v in per_row.items()}
            if len(set(values.values())) == 1 and len(values) == len(rows):
                notes.append(f"{head}: {next(iter(values.values()))} in every row.")
            else:
                notes.append(f"{head}: " + "; ".join(f"{label} → {v}" for label, v in values.items()) + ".")
    return notes, bool(proxies)


def _order(item: tuple[str, list[str]]) -> int:
    return {"official": 0, "approximate": 1, "mixed": 2}.get(item[0], 3)


def build_table(rows: list[Row], layout: LayoutConfig, settings: Settings | None = None) -> Table:
    """Columns from the layout (plus discovered ones), factors in order of first appearance, then per cell its
    mean and uncertainty and per column the marks the tests earn (``stats.analyse``), and the notes."""
    logged = {m for r in rows for t in r.trials for m in t.metrics}
    columns = resolve_columns(layout, logged)
    factors = list(dict.fromkeys(f for r in rows for f in r.factors))
    metrics = [(c.metric, c.direction) for c in columns]
    a = analyse([row_input(r) for r in rows], metrics, settings or Settings(), layout.precision)
    notes, proxy = table_notes(rows, columns, layout.encoders)
    title = layout.title or layout.name
    title += " (proxy)" if proxy and "proxy" not in title.lower() else ""
    return Table(title, factors, columns, rows, layout.precision, a.cells, a.marks, a.legend, notes)
