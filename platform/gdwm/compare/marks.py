"""Which cells of a column are bold (best) and underlined (second): the marking rule, ``compare.marks``.

- ``value``: bold the best printed value, underline the second, as papers do; rows that print the same share.
- ``significance``: walk the rows in value order. The best row is bold, and so is each next row until one is
  significantly worse than the best (the pair's p-value, adjusted for every pair of the column, below α); the first
  row not bold opens the underline the same way. A row therefore never gets a better mark than a row with a better
  value, and a mark is shared only where the tests cannot tell the rows apart.
- ``auto`` (the default): ``significance`` in a column where every compared row of the table's own has per-sample
  data or at least 2 seeds, ``value`` otherwise.

Reported rows (values copied from papers) have nothing to test: they take part by value only, so a reported row
between two of the table's own rows ends a shared mark there. Ties at the printed precision always share.

The multiple-comparison control (``args.correction``) adjusts the p-values of all pairs of a column together:
``holm`` (Holm's step-down, the default: it controls the family-wise error like Bonferroni and rejects at least as
often), ``bonferroni``, or ``none``. Written out here: scipy ships only the false-discovery controls
(``scipy.stats.false_discovery_control``), and Holm is a few lines.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from decimal import Decimal
from typing import TypeVar

from gdwm.compare.layout import Correction, Direction, Rule

__all__ = ["BEST", "SECOND", "Correction", "Decision", "Entry", "Rule", "adjust", "column_marks", "order"]

BEST, SECOND = "best", "second"
K = TypeVar("K", bound=Hashable)


CORRECTION_NAMES = {Correction.holm: "Holm", Correction.bonferroni: "Bonferroni", Correction.none: "no correction"}


def adjust(pvalues: Mapping[K, float], correction: Correction) -> dict[K, float]:
    """Adjusted p-values of one family: reject a hypothesis where its adjusted p < α.

    Holm: sort ascending; the k-th smallest (from 0) becomes ``max`` over j <= k of ``(m - j) * p_(j)``, capped at 1."""
    m, correction = len(pvalues), Correction(correction)
    if correction is Correction.none:
        return dict(pvalues)
    if correction is Correction.bonferroni:
        return {k: min(1.0, p * m) for k, p in pvalues.items()}
    out, running = {}, 0.0
    for j, (k, p) in enumerate(sorted(pvalues.items(), key=lambda kv: kv[1])):
        running = max(running, min(1.0, (m - j) * p))
        out[k] = running
    return out


@dataclass(frozen=True)
class Entry:
    """A row as one column's marking sees it."""

    value: float
    """The cell's value (the mean over its seeds)."""
    shown: Decimal
    """The value as printed: rows that print the same tie."""
    tested: bool = False
    """Takes part in the significance walk (a row of the table's own, in a column marked by significance)."""


@dataclass
class Decision:
    """How one column was marked: for ``gdwm compare``'s legend, its CSV and whoever reads the table's data."""

    rule: Rule
    """``value`` or ``significance`` (what ``auto`` chose; ``value`` when fewer than 2 rows could be tested)."""
    marks: dict[int, str] = field(default_factory=dict)
    """Row index -> ``best`` | ``second``."""
    pvalues: dict[tuple[int, int], float] = field(default_factory=dict)
    """(row a, row b), a < b -> the two-sided p-value of their difference (the pairs that could be tested)."""
    adjusted: dict[tuple[int, int], float] = field(default_factory=dict)
    """The same pairs' p-values after the column's multiple-comparison correction."""
    tests: set[str] = field(default_factory=set)
    """Which tests gave the p-values: ``bootstrap``, ``bootstrap+welch``, ``welch``; ``untested`` for pairs that
    have neither per-sample data nor 2 seeds on both sides (they cannot be told apart)."""


def order(entries: Mapping[int, Entry], direction: Direction) -> list[list[int]]:
    """Rows grouped by printed value, best group first; inside a group, best exact value first (then row order)."""
    sign = -1 if direction is Direction.higher else 1
    ranked = sorted(entries, key=lambda i: (sign * entries[i].shown, sign * entries[i].value, i))
    levels: list[list[int]] = []
    for i in ranked:
        if levels and entries[levels[-1][0]].shown == entries[i].shown:
            levels[-1].append(i)
        else:
            levels.append([i])
    return levels


def column_marks(
    entries: Mapping[int, Entry], direction: Direction, worse: Callable[[int, int], bool] | None = None
) -> dict[int, str]:
    """``best`` / ``second`` by the walk the module describes. ``worse(a, b)``: row b is significantly worse than
    row a (only asked of two ``tested`` rows, a ahead of b in value order); None marks by value alone. No marks when
    every row prints the same value."""
    levels = order(entries, direction)
    if len(levels) < 2:
        return {}
    marks: dict[int, str] = {}
    for mark in (BEST, SECOND):
        if not levels:
            break
        lead = levels.pop(0)
        marks |= dict.fromkeys(lead, mark)
        if worse is None or not all(entries[a].tested for a in lead):
            continue
        while levels and all(entries[b].tested and not any(worse(a, b) for a in lead) for b in levels[0]):
            marks |= dict.fromkeys(levels.pop(0), mark)
    return marks
