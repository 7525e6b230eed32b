"""Table layouts (``conf/compare/<name>.yaml``) and the arguments of ``gdwm compare`` (``conf/args/compare.yaml``).

A layout lists metric columns in order, each with a header, a group (the paper's two-row headers: RD&P, 2D VG, ...)
and a direction; ``discover`` adds every logged metric under a prefix, grouped by its middle part
(``gen/<target>/<metric>``), as the generation tables need one group per target.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Annotated

from annotated_types import Ge, Interval


class Direction(StrEnum):
    higher = "higher"
    lower = "lower"


class Format(StrEnum):
    terminal = "terminal"
    markdown = "markdown"
    latex = "latex"
    csv = "csv"
    html = "html"


class Rule(StrEnum):
    """How a column's best and second rows are chosen (``compare.marks``; ``gdwm.compare.marks``)."""

    auto = "auto"
    value = "value"
    significance = "significance"


class Correction(StrEnum):
    """Multiple-comparison control over the pairs of a column (``args.correction``)."""

    holm = "holm"
    bonferroni = "bonferroni"
    none = "none"


class BootstrapMethod(StrEnum):
    BCa = "BCa"
    percentile = "percentile"
    basic = "basic"


LOWER_IS_BETTER = {"mae", "fid", "fvd", "depth_absrel", "depth_rmse"}


def default_direction(metric: str) -> Direction:
    """MAE, FID, FVD, Fréchet distances, AbsRel and RMSE are lower-is-better (README, Metrics); the rest higher."""
    leaf = metric.rsplit("/", 1)[-1]
    return Direction.lower if leaf in LOWER_IS_BETTER or leaf.startswith("fd_") else Direction.higher


@dataclass
class ColumnConfig:
    """One metric column; its metric name is the key in ``columns``."""

    header: str | None = None
    """Column header; null = the metric's last path part."""
    group: str = ""
    """Group header spanning consecutive columns (e.g. ``RD&P``); empty = none."""
    direction: Direction | None = None
    """``higher`` or ``lower`` is better; null = from the name (mae, fid, fvd, fd_*, depth_absrel/rmse: lower)."""
    mean_of: list[str] = field(default_factory=list)
    """An aggregate column (Avg.): the mean of these metrics as printed (``-name`` enters negated, as an error
    metric does in a score that rewards accuracy), recomputed for every row that has them all, reported rows
    included; empty = as logged."""


@dataclass
class LayoutConfig:
    """A comparison table: metric columns in order (``conf/compare/<name>.yaml``)."""

    name: str = "custom"
    """Layout name (file names of the outputs)."""
    title: str = ""
    """Caption of the table and report."""
    columns: dict[str, ColumnConfig] = field(default_factory=dict)
    """Metric name -> column, in table order."""
    discover: str | None = None
    """Also add a column for every logged metric ``<discover><group>/<leaf>`` (e.g. ``gen/``), grouped by group."""
    headers: dict[str, str] = field(default_factory=dict)
    """Headers of discovered columns by leaf name (e.g. ``depth_absrel: AbsRel``)."""
    order: list[str] = field(default_factory=list)
    """Order of discovered leaves inside a group, as fnmatch patterns (e.g. ``fd_*``); the rest follow, sorted."""
    precision: Annotated[int, Interval(ge=0, le=15)] = 2
    """Decimals shown; a column whose values all print the same gets no marks."""
    encoders: list[str] = field(default_factory=list)
    """Trial params naming the encoders a row used (e.g. ``stage.distill.encoder``): the notes print them per row."""
    marks: Rule = Rule.auto
    """Marking rule: ``value`` (best and second value, as papers do), ``significance`` (shared where the tests cannot
    tell rows apart, monotone in value), ``auto`` (per column: significance where every row of the table's own has
    per-sample data or >= 2 seeds, else value). Reported rows are marked by value in every rule."""
    references: str | None = None
    """A CSV or YAML file of reported rows (numbers copied from papers, with their source) shown beside the runs'
    rows (``gdwm.compare.references``)."""


@dataclass
class CompareArgs:
    """``gdwm compare [args.sweep=NAME | args.runs=[ID,...] | args.filter="..."] [compare=LAYOUT] ...``."""

    sweep: str | None = None
    """Compare the trials of the latest sweep with this name (parent run tagged ``gdwm.sweep``)."""
    runs: list[str] = field(default_factory=list)
    """Compare these run ids, in this order."""
    filter: str | None = None
    """Compare the runs an MLflow filter string selects, e.g. "tags.`gdwm.pipeline` = 'my_pipeline'"."""
    baseline: str | None = None
    """Row label or run id the deltas are taken against; null = the first row that did not fail."""
    factors: list[str] = field(default_factory=list)
    """Param keys shown as factor columns (for runs without ``gdwm.factor.*`` tags), e.g. model.selector.name."""
    out: str | None = None
    """Output folder; null = ``<workdir>/reports/<sweep name | runs | filter | all>``."""
    formats: list[Format] = field(default_factory=lambda: list(Format))
    """What to produce: terminal, markdown, latex, csv, html."""
    alpha: Annotated[float, Interval(gt=0, lt=1)] = 0.05
    """Significance level of the tests behind bold/underline (paired bootstrap, else Welch's t-test over seeds)."""
    confidence: Annotated[float, Interval(gt=0, lt=1)] = 0.95
    """Coverage of the cells' intervals (bootstrap over held-out samples, Student's t over seeds)."""
    resamples: Annotated[int, Ge(2)] = 1000
    """Bootstrap resamples; each one rescores every row's per-sample predictions once."""
    stats_seed: Annotated[int, Interval(ge=0, le=2**32 - 1)] = 0
    """Seed of the bootstrap's resampling: the same runs give the same intervals and marks."""
    bootstrap_method: BootstrapMethod = BootstrapMethod.BCa
    """``BCa`` (its jackknife rescores every row once per held-out sample), ``percentile`` or ``basic``."""
    correction: Correction = Correction.holm
    """Multiple-comparison control over the pairs of a column behind the significance marks: ``holm``,
    ``bonferroni`` or ``none`` (the legend names it)."""
    log_references: bool = False
    """Also log ``compare.references``' rows as runs tagged ``gdwm.kind=reference`` (under the sweep run with
    ``args.sweep``), so later comparisons show them without the file."""


@dataclass(frozen=True)
class Column:
    metric: str
    header: str
    group: str
    direction: Direction
    mean_of: tuple[tuple[str, int], ...] = ()
    """(metric, sign) of an aggregate column's parts; empty for a plain column."""

    @property
    def arrow(self) -> str:
        return "↑" if self.direction is Direction.higher else "↓"

    @property
    def label(self) -> str:
        """One-line header: ``RD&P BLEU ↑``."""
        return " ".join(filter(None, (self.group, self.header, self.arrow)))


def _natural(s: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def parts(column: ColumnConfig) -> tuple[tuple[str, int], ...]:
    """(metric, sign) of ``mean_of``: ``-suite/mae`` -> (``suite/mae``, -1)."""
    return tuple((p[1:], -1) if p.startswith("-") else (p, 1) for p in column.mean_of)


def resolve_columns(layout: LayoutConfig, logged: Iterable[str]) -> list[Column]:
    """The layout's columns, then the discovered ones (groups in natural order, leaves by ``order``)."""
    cols = [
        Column(m, c.header or m.rsplit("/", 1)[-1], c.group, Direction(c.direction or default_direction(m)), parts(c))
        for m, c in layout.columns.items()
    ]
    if layout.discover:
        fixed = set(layout.columns)
        found = {
            m for m in logged if m.startswith(layout.discover) and m not in fixed and "/" in m[len(layout.discover) :]
        }

        def rank(metric: str) -> tuple:
            group, leaf = metric[len(layout.discover) :].rsplit("/", 1)
            pos = next((i for i, p in enumerate(layout.order) if fnmatch.fnmatchcase(leaf, p)), len(layout.order))
            return _natural(group), pos, leaf

        for m in sorted(found, key=rank):
            group, leaf = m[len(layout.discover) :].rsplit("/", 1)
            header = layout.headers.get(leaf) or (f"FD ({leaf[3:]})" if leaf.startswith("fd_") else leaf)
            cols.append(Column(m, header, group, default_direction(m)))
    return cols
