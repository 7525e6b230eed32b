"""The comparison table: factor columns, grouped metric columns, cells with their uncertainty, earned marks.

A cell is the mean over a row's finished seeds with its std (or, for one seed, a bootstrap interval over the
held-out samples); a reported row's cell is the published value. Bold / underline follow the column's marking rule
(``marks``: by value, or by significance tests from ``stats``), and ``legend`` says which rule each column used.
Missing values and failed rows never get or take a mark. Values print rounded half up, as the paper's tables do, and
an aggregate column (the layout's ``mean_of``: Avg.) is the mean of the row's printed cells (``rounding``).
``notes`` (every format prints them under the legend) say which metrics are official or approximate and which
stand on proxy data (from the trials' evaluation stage runs; a proxy table's title says so), which encoders each
row used (the layout's ``encoders`` params), and where the reported rows come from.

The computed table is plain data for whoever reads it further (the renderers, the HTML report, MLflow logging):
``rows[i]`` (label, run id, factors, ``source`` for a reported row), ``columns`` (metric, header, group, direction),
``cells[(i, metric)]`` (``Cell``: mean, n, std, ci_low, ci_high, interval kind), ``marks[(i, metric)]`` and
``decisions[metric]`` (``marks.Decision``: the rule used, the pairs' raw and adjusted p-values).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import groupby

from gdwm.compare.layout import Column, Direction, LayoutConfig, resolve_columns
from gdwm.compare.legend import CHARS, KEY, KEY_CHARS, legend
from gdwm.compare.marks import BEST, SECOND, Decision
from gdwm.compare.rounding import fmt
from gdwm.compare.runs import Row
from gdwm.compare.stats import Cell, RowInput, Seed, Settings, analyse

__all__ = ["BEST", "CHARS", "MISSING", "SECOND", "Table", "build_table", "normalise"]

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
    decisions: dict[str, Decision] = field(default_factory=dict)
    """metric -> how its column was marked: rule, marks, the pairs' raw and adjusted p-values."""
    explanation: str = ""
    """The legend after its key: which rule and test gave the marks, what the cells are (``legend.legend``)."""
    notes: list[str] = field(default_factory=list)
    """Official / approximate metrics, proxy data, encoders per row, sources of reported rows (``table_notes``);
    every format prints them."""

    @property
    def marks(self) -> dict[tuple[int, str], str]:
        """(row index, metric) -> ``best`` | ``second``."""
        return {(i, m): mark for m, d in self.decisions.items() for i, mark in d.marks.items()}

    def legend_text(self, chars: bool = False) -> str:
        """The legend with the key to the marks: typeset (bold, underline) or as characters (``*``, ``†``)."""
        key = (KEY_CHARS if chars else KEY) if any(d.marks for d in self.decisions.values()) else ""
        return " ".join(x for x in (key, self.explanation) if x)

    @property
    def legend(self) -> str:
        """What the marks and cells mean, for the formats that typeset marks; every format prints it."""
        return self.legend_text()

    @property
    def reported(self) -> bool:
        """Some row is reported (copied from a paper): the formats add a source column."""
        return any(r.reported for r in self.rows)

    def source(self, i: int) -> str:
        return str(self.rows[i].source) if self.rows[i].source else ""

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

    def text(self, i: int, metric: str, chars: bool = False) -> str:
        """The cell as one line: ``35.10 ± 1.20 (n=2)``; ``chars``: its mark as a character after the value."""
        value, unc, count = self.parts(i, metric)
        if chars:
            value += CHARS.get(self.marks.get((i, metric), ""), "")
        return " ".join(filter(None, (value, unc, count)))

    def factor(self, i: int, name: str) -> str:
        """The row's value of a factor; ``–`` where it has none, empty for a reported row (it has no factors)."""
        return self.rows[i].factors.get(name, "" if self.rows[i].reported else MISSING)

    @property
    def lead_names(self) -> list[str]:
        """Headers of the columns before the metrics: ``row``, the factors, ``source`` when a row is reported."""
        return ["row", *self.factors, *(["source"] if self.reported else [])]

    def lead(self, i: int) -> list[str]:
        """Row ``i``'s cells before the metrics (``lead_names``)."""
        return [self.rows[i].label, *(self.factor(i, f) for f in self.factors), *([self.source(i)] * self.reported)]

    def block_ends(self, i: int) -> bool:
        """Row ``i`` is the last reported row and own rows follow: the formats draw a rule under it."""
        nxt = i + 1
        return self.rows[i].reported and nxt < len(self.rows) and not self.rows[nxt].reported

    @property
    def caption(self) -> list[str]:
        """The legend, then the notes: the lines every format prints under the table."""
        return self.caption_lines()

    def caption_lines(self, chars: bool = False) -> list[str]:
        return [x for x in (self.legend_text(chars), *self.notes) if x]

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
    """What the statistics need of a row: its counted trials' metrics and sample sets, planned seeds, failure,
    whether it is reported."""
    seeds = [Seed(t.metrics, t.samples, t.seed) for t in row.counted]
    return RowInput(row.label, seeds, row.planned, row.failed, row.reported)


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
        per_row = {r.label: [r.param(k) for k in encoders] for r in rows if not r.reported}
        per_row = {label: v for label, v in per_row.items() if any(x is not None for x in v)}
        if per_row:
            head = f"Encoders ({', '.join(encoders)})"
            values = {label: ", ".join(MISSING if x is None else x for x in v) for label, v in per_row.items()}
            if len(set(values.values())) == 1 and len(values) == sum(not r.reported for r in rows):
                notes.append(f"{head}: {next(iter(values.values()))} in every row.")
            else:
                notes.append(f"{head}: " + "; ".join(f"{label} → {v}" for label, v in values.items()) + ".")
    tables = {}
    for r in rows:
        if r.source and r.source.table:
            tables.setdefault(r.source.table, []).append(r.label)
    if len(tables) == 1 and sum(len(v) for v in tables.values()) == sum(r.reported for r in rows):
        notes.append(f"Reported rows are copied from {next(iter(tables))}.")
    elif tables:
        where = "; ".join(f"{t}: {', '.join(labels)}" for t, labels in tables.items())
        notes.append(f"Reported rows are copied from: {where}.")
    return notes, bool(proxies)


def _order(item: tuple[str, list[str]]) -> int:
    return {"official": 0, "approximate": 1, "mixed": 2}.get(item[0], 3)


def build_table(rows: list[Row], layout: LayoutConfig, settings: Settings | None = None) -> Table:
    """Columns from the layout (plus discovered ones), reported rows first (a block, as papers list prior work),
    factors in order of first appearance, then per cell its mean and uncertainty (an aggregate column: the mean of
    the row's printed parts), per column the marks of ``layout.marks`` (``stats.analyse``), the legend, the notes."""
    rows = [r for r in rows if r.reported] + [r for r in rows if not r.reported]
    logged = {m for r in rows for t in r.trials for m in t.metrics}
    columns = resolve_columns(layout, logged)
    factors = list(dict.fromkeys(f for r in rows for f in r.factors))
    metrics = [(c.metric, c.direction) for c in columns]
    inputs = [row_input(r) for r in rows]
    settings = settings or Settings()
    means = {c.metric: c.mean_of for c in columns if c.mean_of}
    a = analyse(inputs, metrics, settings, layout.precision, layout.marks, means)
    notes, proxy = table_notes(rows, columns, layout.encoders)
    title = layout.title or layout.name
    title += " (proxy)" if proxy and "proxy" not in title.lower() else ""
    explanation = legend(inputs, a, settings, {c.metric: _name(c) for c in columns}, layout.marks)
    return Table(title, factors, columns, rows, layout.precision, a.cells, a.decisions, explanation, notes)
